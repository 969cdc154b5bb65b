//! `rotorloop run --split`: one run over two "hosts", each with its own iceoryx2 space
//! (`--host`), joined by two link gateways (`rotorloop-link`) over Zenoh on loopback, so
//! that what a network does to the loop can be studied on one machine; and `rotorloop
//! link`, which hands over to the gateway binary (the role binaries and this one never
//! link Zenoh).
//!
//! Start order, so that no sample is sent before the other side can take it: both
//! gateways, until they are connected; the roles of the host without the plant; until
//! the plant's host has the services those roles use (mirrored there by its gateway,
//! which means the other side's Zenoh subscriptions exist); then the plant's host.
//!
//! **Who may join (issue 42).** Loopback is not private: any user of the machine can
//! connect to a port on `127.0.0.1`, and a second user's gateway once received every
//! state of a run and had its torques applied. So a split run's gateways authenticate
//! like gateways across a network: the launcher makes one-time credentials for the run
//! ([`LinkCredentials`]: a password from the kernel's randomness, in files only the run's
//! user can read), the listening gateway gets `--users`, the connecting one `--user` and
//! `--password-file`, and Zenoh refuses a peer without them before anything crosses.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use rotorloop_common::graph::{Role, Topic};
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::signals::shutdown_requested;

use crate::run::member::Member;
use rotorloop_common::role::UsageError;

/// Where each role runs: two hosts, in the order given (the first one's gateway listens).
#[derive(Debug, Clone)]
pub struct Split {
    hosts: Vec<String>,
    role_host: BTreeMap<Role, String>,
    /// The run's link credentials, made by the first [`gateway_command`] (for its domain)
    /// and shared by every gateway started after it, restarts included; removed when the
    /// last clone of the split drops, after the gateways have stopped.
    credentials: Arc<OnceLock<Result<LinkCredentials, String>>>,
}

impl Split {
    /// Parses `ROLES@HOST ...` (e.g. `plant,reference,monitor@a controller@b`): every role
    /// on exactly one host (the monitor only if `monitor`), two hosts.
    pub fn parse(spec: &str, monitor: bool) -> Result<Self, UsageError> {
        let bad = |why: String| {
            UsageError(format!(
                "--split `{spec}` is not allowed: {why} (form ROLES@HOST ..., e.g. \
                 `plant,reference,monitor@a controller@b`)"
            ))
        };
        let (mut hosts, mut role_host) = (Vec::<String>::new(), BTreeMap::new());
        for group in spec.split_whitespace() {
            let (roles, host) =
                group.split_once('@').ok_or_else(|| bad(format!("`{group}` has no @HOST")))?;
            Domain::on_host("d", Some(host)).map_err(|_| {
                bad(format!("host `{host}` must be 1 to 12 characters from a-z 0-9 -"))
            })?;
            if !hosts.iter().any(|h| h == host) {
                hosts.push(host.to_owned());
            }
            for role in roles.split(',') {
                let role: Role = role.parse().map_err(|e| bad(format!("{e}")))?;
                if role_host.insert(role, host.to_owned()).is_some() {
                    return Err(bad(format!("{role} is placed twice")));
                }
            }
        }
        for role in Role::ALL.iter().filter(|r| **r != Role::Monitor || monitor) {
            if !role_host.contains_key(role) {
                return Err(bad(format!("{role} is on no host")));
            }
        }
        if !monitor && role_host.contains_key(&Role::Monitor) {
            return Err(bad("the monitor is placed but --no-monitor is given".into()));
        }
        if hosts.len() != 2 {
            return Err(bad(format!("{} host(s); a split has two", hosts.len())));
        }
        Ok(Self { hosts, role_host, credentials: Arc::default() })
    }

    /// The two hosts, the listening one first.
    pub fn hosts(&self) -> &[String] {
        &self.hosts
    }

    /// The host of `role` (a role or a gateway `link-HOST`).
    pub fn host_of(&self, role: &str) -> Option<&str> {
        match role.strip_prefix("link-") {
            Some(h) => self.hosts.iter().find(|x| *x == h).map(String::as_str),
            None => role.parse().ok().and_then(|r| self.host(r)),
        }
    }

    /// The host of `role`.
    pub fn host(&self, role: Role) -> Option<&str> {
        self.role_host.get(&role).map(String::as_str)
    }

    /// The gateways' names as the launcher knows them (`link-HOST`).
    pub fn gateways(&self) -> Vec<String> {
        self.hosts.iter().map(|h| format!("link-{h}")).collect()
    }

    /// The roles on `host`.
    pub fn roles_on(&self, host: &str) -> Vec<Role> {
        Role::ALL.into_iter().filter(|r| self.host(*r) == Some(host)).collect()
    }

    /// The host that only watches (every role of it is the monitor): its gateway is
    /// read-only.
    pub fn read_only(&self, host: &str) -> bool {
        self.roles_on(host).iter().all(|r| *r == Role::Monitor)
    }

    /// How many subscribers of the state the plant waits for on its host: the roles there
    /// and, when a role elsewhere reads states, the gateway's subscriber.
    pub fn plant_subscribers(&self) -> usize {
        let here = self.host(Role::Plant);
        let readers = Topic::State.subscribers().iter().filter_map(|r| self.host(*r));
        let local = readers.clone().filter(|h| Some(*h) == here).count();
        let remote = readers.into_iter().any(|h| Some(h) != here);
        local + usize::from(remote)
    }

    /// The topics the plant's host must have (mirrored) before its roles start: those the
    /// roles of the other host use.
    pub fn topics_needed_at_plant(&self) -> Vec<Topic> {
        let here = self.host(Role::Plant);
        let remote: Vec<Role> = Role::ALL
            .into_iter()
            .filter(|r| self.host(*r).is_some_and(|h| Some(h) != here))
            .collect();
        Topic::ALL.into_iter().filter(|t| remote.iter().any(|r| r.uses(*t))).collect()
    }

    /// Whether every host's gateway has written its ready file in `dir` (is connected).
    pub fn gateways_ready(&self, dir: &Path) -> bool {
        self.hosts.iter().all(|h| ready_file(dir, h).exists())
    }

    /// The run's link credentials, made for `domain` the first time they are asked for
    /// (the same ones for every later call: one split is one run).
    pub fn credentials(&self, domain: &str) -> Result<&LinkCredentials, String> {
        let made = self.credentials.get_or_init(|| {
            LinkCredentials::create(domain).map_err(|e| {
                format!("cannot write the link's credentials in {CREDENTIALS_PARENT}: {e}")
            })
        });
        made.as_ref().map_err(Clone::clone)
    }

    /// A fault's target that is not a role must be one of this split's gateways.
    pub fn check_fault_target(&self, target: &Member) -> Result<(), UsageError> {
        match target {
            Member::Gateway(h) if !self.hosts.contains(h) => Err(UsageError(format!(
                "--fault link-{h}: no host `{h}` in --split (hosts: {})",
                self.hosts.join(", ")
            ))),
            _ => Ok(()),
        }
    }
}

/// The split of `rotorloop bench --placement cross-host`: the controller on a host of its
/// own, as on a hardware-in-the-loop rig with a separate flight computer.
pub const CROSS_HOST: &str = "plant,reference,monitor@a controller@b";

/// The two gateways of a split started outside a run (the bench's bare round trip over
/// the link); stopped when dropped. Their messages go to `DIR/link-HOST.log`.
#[derive(Debug)]
pub struct Gateways(Vec<(String, std::process::Child)>);

impl Gateways {
    /// Starts both gateways of `split` for `domain` and waits until they are connected.
    pub fn start(split: &Split, domain: &str, dir: &Path) -> anyhow::Result<Self> {
        use anyhow::Context;
        let port = free_port()?;
        let mut g = Self(Vec::new());
        for (i, h) in split.hosts().iter().enumerate() {
            let name = format!("link-{h}");
            let log = gateway_log(dir, &name)?;
            let mut cmd = gateway_command(split, h, domain, port, dir);
            cmd.stdin(std::process::Stdio::null()).stdout(log.try_clone()?).stderr(log);
            g.0.push((name, cmd.spawn().context("cannot start a link gateway")?));
            if i == 0 {
                wait_listening(&mut g.0[0].1, port)?;
            }
        }
        if !wait_until(Duration::from_secs(30), || split.gateways_ready(dir)) {
            anyhow::bail!("the link gateways did not connect within 30 s ({})", dir.display());
        }
        Ok(g)
    }
}

impl Drop for Gateways {
    fn drop(&mut self) {
        for (name, c) in &mut self.0 {
            stop(name, c);
        }
    }
}

/// Where a gateway `name` (`link-HOST`) of a quiet run or of the bench writes its messages:
/// `DIR/NAME.log`, appended to (a gateway restarted by a fault continues its log).
pub fn gateway_log(dir: &Path, name: &str) -> std::io::Result<std::fs::File> {
    rotorloop_common::outdir::append_file(&dir.join(format!("{name}.log")))
}

/// Stops a gateway: SIGTERM, then SIGKILL after 5 s.
pub fn stop(name: &str, c: &mut std::process::Child) {
    if let Ok(None) = c.try_wait() {
        crate::run::policy::signal(c, libc::SIGTERM);
        let stopped = wait_until(Duration::from_secs(5), || !matches!(c.try_wait(), Ok(None)));
        if !stopped {
            eprintln!("launcher: {name} did not stop on SIGTERM within 5 s; killed");
            let _ = c.kill();
        }
        let _ = c.wait();
    }
}

/// The gateway binary beside this executable, or how to build it.
pub fn link_binary() -> Result<PathBuf, UsageError> {
    let exe = std::env::current_exe()
        .map_err(|e| UsageError(format!("cannot find this executable: {e}")))?;
    let bin = exe.with_file_name("rotorloop-link");
    if bin.is_file() {
        Ok(bin)
    } else {
        Err(UsageError(format!(
            "the link gateway `{}` is not built: it is a crate of its own (it brings Zenoh); \
             build it with `cargo build --release --workspace` (or `-p rotorloop-link`)",
            bin.display()
        )))
    }
}

/// `rotorloop link ARGS…`: becomes the gateway (same arguments, same exit code).
pub fn exec_link(args: &[String]) -> anyhow::Result<()> {
    use std::os::unix::process::CommandExt;
    let bin = link_binary()?;
    let err = Command::new(&bin).args(args).exec();
    Err(anyhow::anyhow!("cannot start {}: {err}", bin.display()))
}

/// Whether process `pid` holds a socket listening on TCP port `port` (`/proc/net/tcp` and
/// `tcp6`: a socket in state LISTEN (`0A`) on the port whose inode is one of `pid`'s open
/// files). The launcher starts the connecting gateway only once this holds for the
/// listening one, so it never dials a port that someone else took first.
pub fn holds_port(pid: u32, port: u16) -> bool {
    let wanted = format!(":{port:04X}");
    let inodes: Vec<String> = ["/proc/net/tcp", "/proc/net/tcp6"]
        .iter()
        .filter_map(|f| std::fs::read_to_string(f).ok())
        .flat_map(|t| {
            t.lines()
                .skip(1)
                .filter_map(|l| {
                    let f: Vec<&str> = l.split_whitespace().collect();
                    let listening =
                        f.get(1).is_some_and(|a| a.ends_with(&wanted)) && f.get(3) == Some(&"0A");
                    listening.then(|| f.get(9).map(|i| format!("socket:[{i}]"))).flatten()
                })
                .collect::<Vec<_>>()
        })
        .collect();
    if inodes.is_empty() {
        return false;
    }
    let Ok(fds) = std::fs::read_dir(format!("/proc/{pid}/fd")) else { return false };
    fds.flatten().any(|e| {
        std::fs::read_link(e.path())
            .is_ok_and(|l| inodes.iter().any(|i| l.as_os_str() == i.as_str()))
    })
}

/// Waits until the listening gateway `child` holds `port`: `Ok` once it does, or why not
/// (it exited: the port taken, its messages say; or 30 s passed). What the connecting
/// gateway is started after.
pub fn wait_listening(child: &mut std::process::Child, port: u16) -> anyhow::Result<()> {
    let gone = |c: &mut std::process::Child| !matches!(c.try_wait(), Ok(None));
    wait_until(Duration::from_secs(30), || holds_port(child.id(), port) || gone(child));
    if holds_port(child.id(), port) {
        return Ok(());
    }
    anyhow::bail!(
        "the listening link gateway does not hold 127.0.0.1:{port} (another process may have \
         taken the port before it; its messages are above): the connecting one was not started"
    )
}

/// The listening gateway's port: `--link-port`, or a free one ([`free_port`]).
pub fn port(asked: Option<u16>) -> anyhow::Result<u16> {
    asked.map_or_else(free_port, Ok)
}

/// A free TCP port on loopback (bound, read, released) for the first host's gateway.
pub fn free_port() -> anyhow::Result<u16> {
    let l = std::net::TcpListener::bind("127.0.0.1:0")?;
    Ok(l.local_addr()?.port())
}

/// The command line of `host`'s gateway: the first host listens on `port`, the second
/// connects to it, both with the run's credentials ([`LinkCredentials`], made for `domain`
/// by the first call); a host with only the monitor is read-only. (The launcher checked with
/// [`link_binary`] that the binary is there.)
///
/// Credentials that cannot be written fail closed: the launcher says why, and the gateway
/// is pointed at a path that cannot exist (under `/dev/null`), so it stops (exit 2,
/// naming it) rather than listen without them.
pub fn gateway_command(split: &Split, host: &str, domain: &str, port: u16, out: &Path) -> Command {
    let bin = link_binary().unwrap_or_else(|_| PathBuf::from("rotorloop-link"));
    let mut cmd = Command::new(bin);
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let listens = split.hosts[0] == host;
    let side = if listens { "--listen" } else { "--connect" };
    cmd.args(["--domain", domain, "--host", host, side, &endpoint]);
    let dir = match split.credentials(domain) {
        Ok(c) => c.dir().to_owned(),
        Err(e) => {
            eprintln!("launcher: error: {e}; the link-{host} gateway will not start without them");
            PathBuf::from(NO_CREDENTIALS)
        }
    };
    match listens {
        true => cmd.arg("--users").arg(dir.join(USERS_FILE)),
        false => cmd.args(["--user", LINK_USER, "--password-file"]).arg(dir.join(PASSWORD_FILE)),
    };
    cmd.arg("--ready-file").arg(ready_file(out, host));
    if split.read_only(host) {
        cmd.arg("--read-only");
    }
    cmd
}

/// The user name of a split run's gateways (the password is what is secret).
pub const LINK_USER: &str = "rotorloop";
/// Where a split run's credentials live: beside the domain's other private files, in a
/// directory `rotorloop-link-DOMAIN-XXXXXXXX` made exclusively (mode 0700) under a name
/// another user cannot guess. `/dev/shm` is sticky: no other user can remove or replace it.
pub const CREDENTIALS_PARENT: &str = "/dev/shm";
const USERS_FILE: &str = "users";
const PASSWORD_FILE: &str = "password";
/// Where a gateway whose credentials could not be written looks for them: under a file,
/// so nothing can ever be there.
const NO_CREDENTIALS: &str = "/dev/null/link-credentials-not-written";

/// The prefix of the names of `domain`'s credential directories in [`CREDENTIALS_PARENT`].
pub fn credentials_prefix(domain: &str) -> String {
    format!("rotorloop-link-{domain}-")
}

/// One split run's link credentials (module docs): the user [`LINK_USER`] and a password
/// of 32 bytes from the kernel's randomness (`getrandom`), hex, never on a command line.
/// They live in `/dev/shm/rotorloop-link-DOMAIN-XXXXXXXX/` (never in OUT, which the run's
/// user may share: made for this run with `mkdir` mode 0700 under a random name, owned by
/// the run's user: a second user can neither guess, list, enter, remove nor replace it) as
/// `users` (`user:password`, the listening gateway's `--users`) and `password` (the
/// connecting gateway's `--password-file`), each mode 0600, created with
/// `O_EXCL|O_NOFOLLOW`. Dropping them removes both files and the directory; a launcher
/// killed with SIGKILL leaves them, and the next run of the domain removes them (its
/// user's own only: the password of a run that ended opens nothing).
#[derive(Debug)]
pub struct LinkCredentials {
    dir: PathBuf,
}

impl LinkCredentials {
    /// Makes fresh credentials for `domain`, removing what an earlier run of this user on
    /// the domain left.
    pub fn create(domain: &str) -> std::io::Result<Self> {
        use std::os::unix::fs::{DirBuilderExt, MetadataExt};
        let prefix = credentials_prefix(domain);
        let me = rotorloop_common::private::euid();
        for e in std::fs::read_dir(CREDENTIALS_PARENT)?.flatten() {
            let stale = e.file_name().to_str().is_some_and(|n| n.starts_with(&prefix));
            // A killed run's leftovers of this user's (another user's are never touched).
            let ours = e.path().symlink_metadata().is_ok_and(|m| m.is_dir() && m.uid() == me);
            if stale && ours {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
        let dir = loop {
            let dir = Path::new(CREDENTIALS_PARENT)
                .join(format!("{prefix}{}", rotorloop_common::private::random_name(8)));
            match std::fs::DirBuilder::new().mode(0o700).create(&dir) {
                Ok(()) => break dir,
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(e),
            }
        };
        let meta = std::fs::symlink_metadata(&dir)?;
        let made = Self { dir };
        if !meta.is_dir() || meta.uid() != me || meta.mode() & 0o077 != 0 {
            return Err(std::io::Error::other(format!(
                "{} is not a private directory of this user (mode {:o}, owner {}): its \
                 file system may not keep Unix permissions",
                made.dir.display(),
                meta.mode() & 0o7777,
                meta.uid()
            )));
        }
        let password =
            rotorloop_common::private::hex(&rotorloop_common::private::random_bytes::<32>()?);
        let write = |name: &str, text: String| {
            rotorloop_common::private::write_new(&made.dir.join(name), text.as_bytes())
                .map_err(std::io::Error::other)
        };
        write(USERS_FILE, format!("{LINK_USER}:{password}\n"))?;
        write(PASSWORD_FILE, format!("{password}\n"))?;
        Ok(made)
    }

    /// The directory that holds them.
    pub fn dir(&self) -> &Path {
        &self.dir
    }
}

impl Drop for LinkCredentials {
    fn drop(&mut self) {
        // Its name is random and /dev/shm sticky: it is still the one made here.
        for f in [USERS_FILE, PASSWORD_FILE] {
            let _ = std::fs::remove_file(self.dir.join(f));
        }
        let _ = std::fs::remove_dir(&self.dir);
    }
}

/// Where `host`'s gateway says it is connected.
pub fn ready_file(out: &Path, host: &str) -> PathBuf {
    out.join(format!(".link-{host}.ready"))
}

/// Waits until `ready()` holds, a termination signal, or `timeout`; false unless ready.
pub fn wait_until(timeout: Duration, mut ready: impl FnMut() -> bool) -> bool {
    let start = Instant::now();
    while !ready() {
        if shutdown_requested() || start.elapsed() > timeout {
            return false;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_split_places_every_role_once_on_one_of_two_hosts() {
        let s = Split::parse("plant,reference,monitor@a controller@b", true).expect("valid");
        assert_eq!(s.hosts(), ["a", "b"]);
        assert_eq!(s.host_of("controller"), Some("b"));
        assert_eq!(s.host_of("link-a"), Some("a"));
        assert_eq!(s.plant_subscribers(), 3); // reference, monitor, the gateway
        assert_eq!(s.topics_needed_at_plant(), [Topic::State, Topic::Reference, Topic::Torque]);
        assert!(!s.read_only("b"));
        let m = Split::parse("plant,reference,controller@a monitor@ground", true).expect("valid");
        assert!(m.read_only("ground") && !m.read_only("a"));
        assert_eq!(m.plant_subscribers(), 3);
        for (spec, why) in [
            ("plant,reference,controller,monitor@a", "two"),
            ("plant,reference@a controller@b", "monitor is on no host"),
            ("plant,reference,monitor@a controller,plant@b", "placed twice"),
            ("plant,reference,monitor@a pilot@b", "not a role"),
            ("plant,reference,monitor@A controller@b", "host `A`"),
            ("plant,reference,monitor controller@b", "no @HOST"),
        ] {
            let e = Split::parse(spec, true).expect_err(spec).to_string();
            assert!(e.contains(why), "{spec}: {e}");
        }
        let gateway = |h: &str| Member::Gateway(h.into());
        assert!(s.check_fault_target(&gateway("c")).is_err());
        assert!(s.check_fault_target(&gateway("b")).is_ok());
    }

    /// A split run's credentials are readable by its user only (directory 0700, files
    /// 0600), never in OUT but in a directory of the domain's with a random name, fresh for
    /// every run (an earlier run's are removed), agree between the two gateways' files,
    /// reach both command lines and never as the password itself, and are gone once the
    /// split that made them is.
    #[test]
    fn a_runs_link_credentials_are_private_fresh_and_removed_with_it() {
        use std::os::unix::fs::PermissionsExt;
        let domain = format!("t-cred-{}", std::process::id());
        let mode = |p: &Path| std::fs::metadata(p).expect("exists").permissions().mode() & 0o777;
        let read = |p: PathBuf| std::fs::read_to_string(p).expect("read");
        let out = tempfile::tempdir().expect("tempdir");
        let mut passwords = Vec::new();
        let mut dirs = Vec::new();
        for _ in 0..2 {
            let s = Split::parse("plant,reference,monitor@a controller@b", true).expect("valid");
            let argv = |host| {
                let cmd = gateway_command(&s, host, &domain, 7447, out.path());
                cmd.get_args().map(|a| a.to_string_lossy().into_owned()).collect::<Vec<_>>()
            };
            let (a, b) = (argv("a"), argv("b"));
            let dir = s.credentials(&domain).expect("made").dir().to_owned();
            let name = dir.file_name().expect("name").to_string_lossy().into_owned();
            assert!(dir.starts_with(CREDENTIALS_PARENT) && !dir.starts_with(out.path()));
            let tail = name.strip_prefix(&credentials_prefix(&domain)).expect("prefix");
            assert_eq!(tail.len(), 8, "{name}: a random tail");
            let users = dir.join(USERS_FILE).display().to_string();
            let pw_file = dir.join(PASSWORD_FILE).display().to_string();
            assert!(a.windows(2).any(|w| w == ["--users", users.as_str()]), "{a:?}");
            assert!(b.windows(2).any(|w| w == ["--user", LINK_USER]), "{b:?}");
            assert!(b.windows(2).any(|w| w == ["--password-file", pw_file.as_str()]), "{b:?}");
            assert_eq!(mode(&dir), 0o700);
            assert_eq!(mode(&dir.join(USERS_FILE)), 0o600);
            assert_eq!(mode(&dir.join(PASSWORD_FILE)), 0o600);
            let password = read(dir.join(PASSWORD_FILE)).trim_end().to_owned();
            assert_eq!(password.len(), 64, "32 random bytes in hex");
            assert_eq!(read(dir.join(USERS_FILE)), format!("{LINK_USER}:{password}\n"));
            assert!(!a.iter().chain(&b).any(|x| x.contains(&password)), "on a command line");
            passwords.push(password);
            dirs.push(dir);
            // The first run's launcher is killed (its credentials are never dropped): the
            // second run of the domain removes them.
            std::mem::forget(s);
        }
        assert_ne!(passwords[0], passwords[1], "each run has its own");
        assert!(!dirs[0].exists(), "a killed run's credentials were left");
        let _ = std::fs::remove_dir_all(&dirs[1]);
        let s = Split::parse("plant,reference,monitor@a controller@b", true).expect("valid");
        let dir = s.credentials(&domain).expect("made").dir().to_owned();
        let clone = s.clone();
        drop(s);
        assert!(dir.exists(), "a clone of the split (the bench's gateways) still uses them");
        drop(clone);
        assert!(!dir.exists(), "{} left after the run", dir.display());
    }
}
