//! The gateway's arguments and the Zenoh configuration they make, with the rules of who
//! may join: loopback unless authenticated, and an explicit direction.
//!
//! - **Endpoints.** Every `listen` and `connect` endpoint must be on loopback
//!   (`127.0.0.0/8`, `::1`, `localhost`) unless the session authenticates its peers:
//!   Zenoh's user/password (`--users FILE` on the listening side, `--user` and
//!   `--password-file` on the connecting side) or TLS with client certificates
//!   (`transport.link.tls.enable_mtls` in a `--zenoh` file). A session that would listen or
//!   connect beyond this machine without either is refused before it opens.
//! - **Scouting.** Never multicast scouting, whatever a `--zenoh` file says: a gateway
//!   connects only to the endpoints it is given.
//! - **Direction.** `--read-only` (a remote monitor or ground station): the session may
//!   put nothing (Zenoh access control, egress `put` and `delete` denied on every key),
//!   so no sample or event of this host ever enters the loop; it still receives
//!   everything the loop exports. The rule is this gateway's own: it keeps this host out
//!   of the loop, not another gateway that holds the same password.
//! - **Secrets.** A users or password file that others than its owner may read or write is
//!   used, with a warning naming the file and its mode ([`loose_secret_files`]).

use std::path::PathBuf;

use clap::{Args, ValueEnum};

/// A configuration the gateway refuses (exit code 2).
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// A non-loopback endpoint without authentication.
    #[error(
        "{which} endpoint `{endpoint}` is not on loopback and the session does not authenticate \
         its peers: give --users FILE (listening side) or --user NAME --password-file FILE \
         (connecting side), or a --zenoh file with TLS client certificates \
         (transport.link.tls.enable_mtls), or use tcp/127.0.0.1:PORT"
    )]
    Unauthenticated {
        /// `--listen` or `--connect`.
        which: &'static str,
        /// The endpoint given.
        endpoint: String,
    },
    /// Neither an endpoint nor a configuration file.
    #[error(
        "say where to meet the other host: --listen ENDPOINT, --connect ENDPOINT or --zenoh FILE"
    )]
    NoEndpoint,
    /// A bad value.
    #[error("{0}")]
    Bad(String),
}

/// Test hook: how a listening gateway answers the connecting side's question
/// ([`crate::proof`]), to play a peer that completed Zenoh's handshake without the run's
/// password (a Zenoh that does not check it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum TestProof {
    /// No answer.
    Silent,
    /// An answer made with another password.
    Wrong,
}

/// How a gateway waits for work (`--wait`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum GatewayWait {
    /// Blocks until the domain's events or the carrier wake it.
    Event,
    /// Busy-polls: lowest latency, one core busy.
    Spin,
}

/// `rotorloop link` / `rotorloop-link` arguments.
#[derive(Debug, Clone, Args)]
pub struct LinkArgs {
    /// The run domain whose services (`rotorloop/<domain>/…`, only those) are bridged.
    #[arg(long)]
    pub domain: String,
    /// This side's host (`--host` of the roles here) (default: none, the machine's own
    /// iceoryx2 space).
    #[arg(long)]
    pub host: Option<String>,
    /// A Zenoh configuration file (Zenoh's own JSON5); `--listen`/`--connect` add to it.
    #[arg(long)]
    pub zenoh: Option<PathBuf>,
    /// Listen for the other host's gateway here, e.g. `tcp/127.0.0.1:7447`. Repeatable.
    #[arg(long)]
    pub listen: Vec<String>,
    /// Connect to the other host's gateway here, e.g. `tcp/127.0.0.1:7447`. Repeatable.
    #[arg(long)]
    pub connect: Vec<String>,
    /// Listening side: a file of `user:password` lines; peers must authenticate as one.
    #[arg(long)]
    pub users: Option<PathBuf>,
    /// Connecting side: the user name to authenticate as (with `--password-file`).
    #[arg(long)]
    pub user: Option<String>,
    /// Connecting side: a file holding the password (its first line).
    #[arg(long)]
    pub password_file: Option<PathBuf>,
    /// Import the loop's topics and never put anything into it (a remote monitor's host).
    #[arg(long)]
    pub read_only: bool,
    /// Write this file once the other host's gateway is connected (for the launcher).
    #[arg(long)]
    pub ready_file: Option<PathBuf>,
    /// How the gateway waits: `event` (the domain's events and the carrier wake it) or
    /// `spin` (busy-poll: lowest latency, one core busy).
    #[arg(long, value_enum, default_value_t = GatewayWait::Event)]
    pub wait: GatewayWait,
    /// How often the gateway looks for services that appeared or went away (ms). Nothing
    /// crosses while it looks (3-7 ms each on 2 vCPUs; the gateway says at exit): at 20 ms
    /// a fifth of the samples waited behind a discovery. Every 20 ms while nothing is
    /// bridged yet and for 2 s after what is bridged changed. 1 to 60000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 500,
          value_parser = rotorloop_common::input::whole_in(1u64, 60_000, "ms"))]
    pub discover_ms: u64,
    /// Test hook: answer the connecting side's question so (see [`TestProof`]).
    #[arg(long, hide = true, value_enum)]
    pub test_proof: Option<TestProof>,
}

/// Whether a Zenoh endpoint (`proto/address[#…][?…]`) is on loopback.
pub fn is_loopback(endpoint: &str) -> bool {
    let bare = endpoint.split(['#', '?']).next().unwrap_or_default();
    let Some((_, address)) = bare.split_once('/') else { return false };
    // `host:port`, `[v6]:port`, or a unix socket path (which is local by nature).
    if address.starts_with('/') || bare.starts_with("unixsock-stream/") {
        return true;
    }
    let host = match address.rsplit_once(':') {
        Some((h, port)) if port.bytes().all(|b| b.is_ascii_digit()) => h,
        _ => address,
    };
    let host = host.trim_start_matches('[').trim_end_matches(']');
    host == "localhost"
        || host == "::1"
        || host.parse::<std::net::Ipv4Addr>().is_ok_and(|ip| ip.is_loopback())
}

fn bad(what: impl std::fmt::Display) -> ConfigError {
    ConfigError::Bad(what.to_string())
}

fn json_list(items: &[String]) -> String {
    serde_json::to_string(items).unwrap_or_else(|_| "[]".into())
}

/// The endpoints at `key` (`listen/endpoints`, `connect/endpoints`) of a configuration:
/// a list, or a map of lists by mode.
pub fn endpoints(config: &zenoh::Config, key: &str) -> Vec<String> {
    let Ok(text) = config.get_json(key) else { return Vec::new() };
    let value: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
    let mut out = Vec::new();
    let mut push = |v: &serde_json::Value| {
        out.extend(v.as_array().into_iter().flatten().filter_map(|e| e.as_str().map(String::from)));
    };
    match &value {
        serde_json::Value::Object(by_mode) => by_mode.values().for_each(&mut push),
        other => push(other),
    }
    out
}

fn set(config: &mut zenoh::Config, key: &str, json5: &str) -> Result<(), ConfigError> {
    config.insert_json5(key, json5).map_err(|e| bad(format!("Zenoh configuration `{key}`: {e}")))
}

/// A string value of the Zenoh configuration at `key`, if set and not empty.
pub fn config_string(config: &zenoh::Config, key: &str) -> Option<String> {
    let v: serde_json::Value = serde_json::from_str(&config.get_json(key).ok()?).ok()?;
    v.as_str().filter(|s| !s.is_empty()).map(String::from)
}

/// Whether the session authenticates its peers: a user/password dictionary (listening),
/// a user and password (connecting), or TLS client certificates.
fn authenticates(config: &zenoh::Config) -> bool {
    let set = |key: &str| config_string(config, key).is_some();
    let mtls = config.get_json("transport/link/tls/enable_mtls").is_ok_and(|v| v == "true");
    set("transport/auth/usrpwd/dictionary_file")
        || (set("transport/auth/usrpwd/user") && set("transport/auth/usrpwd/password"))
        || mtls
}

/// The files that hold a secret of the session: the users dictionary (`--users` or a
/// `--zenoh` file's `dictionary_file`), `--password-file`, and a `--zenoh` file that
/// holds a password itself.
fn secret_files(args: &LinkArgs, config: &zenoh::Config) -> Vec<(&'static str, PathBuf)> {
    let mut out = Vec::new();
    let dictionary = config_string(config, "transport/auth/usrpwd/dictionary_file");
    match (&args.users, dictionary) {
        (Some(users), _) => out.push(("--users", users.clone())),
        (None, Some(d)) => out.push(("the users file", PathBuf::from(d))),
        _ => {}
    }
    if let Some(file) = &args.password_file {
        out.push(("--password-file", file.clone()));
    } else if let Some(file) = &args.zenoh {
        if config_string(config, "transport/auth/usrpwd/password").is_some() {
            out.push(("--zenoh (it holds a password)", file.clone()));
        }
    }
    out
}

/// A warning for each file holding a secret of the session (the users dictionary, the
/// password) that others than its owner may read or write, naming the file and its mode:
/// whoever reads it can join the loop as a full peer. The gateway still starts (a file
/// may be shared on purpose, e.g. through a group).
pub fn loose_secret_files(args: &LinkArgs, config: &zenoh::Config) -> Vec<String> {
    use std::os::unix::fs::PermissionsExt;
    let mut out = Vec::new();
    for (what, file) in secret_files(args, config) {
        let Ok(meta) = std::fs::metadata(&file) else { continue };
        let mode = meta.permissions().mode() & 0o7777;
        let how = match (mode & 0o044 != 0, mode & 0o022 != 0) {
            (true, true) => "readable and writable by others than its owner",
            (true, false) => "readable by others than its owner",
            (false, true) => "writable by others than its owner",
            (false, false) => continue,
        };
        out.push(format!(
            "{what} {} (mode {mode:04o}) is {how}: whoever can read it can join the loop; \
             make it 0600 (chmod 600 {})",
            file.display(),
            file.display()
        ));
    }
    out
}

/// The access control of a read-only gateway: nothing leaves this session as data.
const READ_ONLY_ACL: &str = r#"{
  enabled: true,
  default_permission: "allow",
  rules: [{ id: "read-only", messages: ["put", "delete"], flows: ["egress"],
            permission: "deny", key_exprs: ["**"] }],
  subjects: [{ id: "every-peer" }],
  policies: [{ rules: ["read-only"], subjects: ["every-peer"] }],
}"#;

/// The Zenoh configuration of `args`, checked (module docs).
pub fn zenoh_config(args: &LinkArgs) -> Result<zenoh::Config, ConfigError> {
    let mut config = match &args.zenoh {
        Some(file) => zenoh::Config::from_file(file)
            .map_err(|e| bad(format!("--zenoh {}: {e}", file.display())))?,
        None => {
            let mut c = zenoh::Config::default();
            set(&mut c, "mode", "\"peer\"")?;
            c
        }
    };
    // A gateway connects only to the endpoints it is given: no multicast scouting, even
    // if a file turns it on (it would announce the loop on the local network).
    set(&mut config, "scouting/multicast/enabled", "false")?;
    // Zenoh's default peer listens on every interface (`tcp/[::]:0`): without a file, a
    // gateway listens only where it is told.
    if !args.listen.is_empty() || args.zenoh.is_none() {
        set(&mut config, "listen/endpoints", &json_list(&args.listen))?;
    }
    if !args.connect.is_empty() {
        set(&mut config, "connect/endpoints", &json_list(&args.connect))?;
    }
    if let Some(users) = &args.users {
        std::fs::metadata(users).map_err(|e| bad(format!("--users {}: {e}", users.display())))?;
        let path = serde_json::Value::from(users.display().to_string()).to_string();
        set(&mut config, "transport/auth/usrpwd/dictionary_file", &path)?;
    }
    match (&args.user, &args.password_file) {
        (Some(user), Some(file)) => {
            let text = std::fs::read_to_string(file)
                .map_err(|e| bad(format!("--password-file {}: {e}", file.display())))?;
            let password = text.lines().next().unwrap_or_default().trim_end();
            if password.is_empty() {
                return Err(bad(format!(
                    "--password-file {}: the first line is empty",
                    file.display()
                )));
            }
            let json = |s: &str| serde_json::Value::from(s).to_string();
            set(&mut config, "transport/auth/usrpwd/user", &json(user))?;
            set(&mut config, "transport/auth/usrpwd/password", &json(password))?;
        }
        (None, None) => {}
        _ => return Err(bad("--user and --password-file go together")),
    }
    if args.read_only {
        set(&mut config, "access_control", READ_ONLY_ACL)?;
    }
    let (listen, connect) =
        (endpoints(&config, "listen/endpoints"), endpoints(&config, "connect/endpoints"));
    if listen.is_empty() && connect.is_empty() {
        return Err(ConfigError::NoEndpoint);
    }
    if !authenticates(&config) {
        let open = |which, list: &[String]| {
            list.iter()
                .find(|e| !is_loopback(e))
                .map(|e| ConfigError::Unauthenticated { which, endpoint: e.clone() })
        };
        if let Some(e) = open("listen", &listen).or_else(|| open("connect", &connect)) {
            return Err(e);
        }
    }
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args() -> LinkArgs {
        LinkArgs {
            domain: "d".into(),
            host: None,
            zenoh: None,
            listen: vec![],
            connect: vec![],
            users: None,
            user: None,
            password_file: None,
            read_only: false,
            ready_file: None,
            wait: GatewayWait::Event,
            discover_ms: 500,
            test_proof: None,
        }
    }

    #[test]
    fn loopback_endpoints_are_told_from_network_ones() {
        for e in ["tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tcp/localhost:7447", "tls/127.0.0.2:1"] {
            assert!(is_loopback(e), "{e}");
        }
        for e in ["tcp/0.0.0.0:7447", "tcp/192.168.1.2:7447", "tcp/[::]:7447", "tcp/example.org:1"]
        {
            assert!(!is_loopback(e), "{e}");
        }
    }

    #[test]
    fn the_example_zenoh_files_authenticate_and_do_not_scout() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/zenoh");
        let mut n = 0;
        for e in std::fs::read_dir(&dir).expect("examples/zenoh").flatten() {
            let a = LinkArgs { zenoh: Some(e.path()), ..args() };
            let c = zenoh_config(&a).unwrap_or_else(|err| panic!("{}: {err}", e.path().display()));
            assert!(authenticates(&c), "{}", e.path().display());
            let scouting = c.get_json("scouting/multicast/enabled").expect("scouting");
            assert_eq!(scouting, "false", "{}", e.path().display());
            n += 1;
        }
        assert_eq!(n, 3, "plant host, controller host, mTLS");
        let tmp = tempfile::tempdir().expect("tempdir");
        let file = tmp.path().join("scouting.json5");
        let text = r#"{ listen: { endpoints: ["tcp/127.0.0.1:7447"] },
                        scouting: { multicast: { enabled: true } } }"#;
        std::fs::write(&file, text).expect("write");
        let c = zenoh_config(&LinkArgs { zenoh: Some(file), ..args() }).expect("loopback");
        let scouting = c.get_json("scouting/multicast/enabled").expect("scouting");
        assert_eq!(scouting, "false", "a file cannot turn multicast scouting on");
    }

    #[test]
    fn a_network_endpoint_without_authentication_is_refused_naming_it() {
        let a = LinkArgs { listen: vec!["tcp/0.0.0.0:7447".into()], ..args() };
        let e = zenoh_config(&a).expect_err("refused").to_string();
        assert!(e.contains("tcp/0.0.0.0:7447") && e.contains("--users"), "{e}");
        let a = LinkArgs { connect: vec!["tcp/10.0.0.5:7447".into()], ..args() };
        assert!(matches!(zenoh_config(&a), Err(ConfigError::Unauthenticated { .. })));
        assert!(matches!(zenoh_config(&args()), Err(ConfigError::NoEndpoint)));
    }

    #[test]
    fn a_network_endpoint_with_user_and_password_is_allowed() {
        let dir = tempfile::tempdir().expect("tempdir");
        let users = dir.path().join("users");
        std::fs::write(&users, "ground:secret\n").expect("write");
        let a = LinkArgs { listen: vec!["tcp/0.0.0.0:7447".into()], users: Some(users), ..args() };
        let c = zenoh_config(&a).expect("allowed");
        assert!(
            c.get_json("transport/auth/usrpwd/dictionary_file").expect("set").contains("users")
        );
        let pw = dir.path().join("pw");
        std::fs::write(&pw, "secret\n").expect("write");
        let a = LinkArgs {
            connect: vec!["tcp/10.0.0.5:7447".into()],
            user: Some("ground".into()),
            password_file: Some(pw),
            ..args()
        };
        let c = zenoh_config(&a).expect("allowed");
        assert_eq!(c.get_json("transport/auth/usrpwd/password").expect("set"), "\"secret\"");
    }

    /// Issue 42: a users or password file that others may read is named, with its mode;
    /// the same files at 0600 give no warning.
    #[test]
    fn a_secret_file_others_can_read_is_warned_about_naming_it_and_its_mode() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().expect("tempdir");
        let (users, pw) = (dir.path().join("users"), dir.path().join("pw"));
        std::fs::write(&users, "ground:secret\n").expect("write");
        std::fs::write(&pw, "secret\n").expect("write");
        let chmod = |p: &std::path::Path, m| {
            std::fs::set_permissions(p, std::fs::Permissions::from_mode(m)).expect("chmod")
        };
        let listening = LinkArgs {
            listen: vec!["tcp/127.0.0.1:7447".into()],
            users: Some(users.clone()),
            ..args()
        };
        let connecting = LinkArgs {
            connect: vec!["tcp/127.0.0.1:7447".into()],
            user: Some("ground".into()),
            password_file: Some(pw.clone()),
            ..args()
        };
        let warnings = |a: &LinkArgs| loose_secret_files(a, &zenoh_config(a).expect("valid"));
        for (file, a, mode) in [(&users, &listening, 0o644), (&pw, &connecting, 0o604)] {
            chmod(file, mode);
            let w = warnings(a);
            assert_eq!(w.len(), 1, "{w:?}");
            let name = file.display().to_string();
            assert!(w[0].contains(&name) && w[0].contains(&format!("{mode:04o}")), "{}", w[0]);
            chmod(file, 0o600);
            assert!(warnings(a).is_empty(), "{:?}", warnings(a));
        }
        chmod(&users, 0o620);
        assert!(warnings(&listening)[0].contains("writable"), "{:?}", warnings(&listening));
    }

    #[test]
    fn a_read_only_gateway_denies_every_outgoing_put() {
        let a = LinkArgs { connect: vec!["tcp/127.0.0.1:7447".into()], read_only: true, ..args() };
        let c = zenoh_config(&a).expect("allowed");
        let acl = c.get_json("access_control").expect("set");
        assert!(
            acl.contains("\"egress\"") && acl.contains("\"put\"") && acl.contains("deny"),
            "{acl}"
        );
        let open = zenoh_config(&LinkArgs { read_only: false, ..a }).expect("allowed");
        assert!(!open.get_json("access_control/enabled").expect("key").contains("true"));
    }
}
