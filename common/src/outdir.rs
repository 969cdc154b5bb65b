//! The one way to write into a run's directory (`--out`, OUT): [`OutDir`] holds OUT as an
//! open directory and makes every file and subdirectory relative to that descriptor, so a
//! name another user swapped for a link is never followed.
//!
//! OUT must be its user's: [`OutDir::make`] and [`OutDir::open`] refuse ([`OutError::NotYours`],
//! exit 2) an OUT not owned by the running user, one another user can write (other-writable,
//! or group-writable by a group with other members), one that is a symbolic link another
//! user owns, and a directory on the way to it that another user owns or can write and is
//! not sticky (the rule of OpenSSH's `StrictModes` and systemd's tmpfiles). A new OUT and
//! its missing parents are made with the user's umask (0755 under the usual 022).
//!
//! Inside OUT, a file written whole ([`OutDir::write`], [`OutDir::atomic`]) goes to a
//! temporary made exclusively (`O_CREAT | O_EXCL | O_NOFOLLOW`) under an unpredictable name
//! (`.NAME.XXXXXXXX.partial`), renamed into place (`renameat`) when complete, and removed
//! on failure or drop; a file written as it grows ([`OutDir::create`]) replaces whatever
//! had its name (`unlinkat`, then `O_EXCL | O_NOFOLLOW`); a subdirectory ([`OutDir::subdir`])
//! is made with `mkdirat` and opened with `O_NOFOLLOW`, then checked like OUT.

use std::ffi::{CStr, CString};
use std::fs::File;
use std::io::Write;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, FromRawFd, OwnedFd};
use std::os::unix::ffi::OsStrExt;
use std::os::unix::fs::MetadataExt;
use std::path::{Component, Path, PathBuf};

use crate::private::{euid, user_name};

/// Why OUT (or a file in it) could not be used.
#[derive(Debug, thiserror::Error)]
pub enum OutError {
    /// OUT, or a directory on the way to it, is another user's to change: refused (exit 2).
    #[error(
        "{path} {why}. A run writes only into a directory that is its own user's and that no \
         other user can change: choose an --out of your own (a new one is made with your \
         umask), or make this one yours (chown {user} {path}; chmod go-w {path})",
        path = .path.display()
    )]
    NotYours {
        /// The path refused.
        path: PathBuf,
        /// What is wrong with it: owner, type, mode.
        why: String,
        /// The running user's name, for the advice.
        user: String,
    },
    /// The system refused.
    #[error("{}: {source}", .path.display())]
    Io {
        /// The path.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
}

impl OutError {
    fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io { path: path.to_path_buf(), source }
    }

    fn not_yours(path: &Path, why: String) -> Self {
        let user = user_name(euid());
        let user = user.split(' ').next().unwrap_or_default().to_owned();
        Self::NotYours { path: path.to_path_buf(), why, user }
    }

    /// Whether this is a refusal (exit 2) rather than the system's error.
    pub fn is_refusal(&self) -> bool {
        matches!(self, Self::NotYours { .. })
    }
}

/// A run's directory, held open: every file in it is made relative to this descriptor.
#[derive(Debug)]
pub struct OutDir {
    fd: OwnedFd,
    path: PathBuf,
}

fn cstr(name: &str) -> std::io::Result<CString> {
    if name.is_empty() || name.contains('/') || name == "." || name == ".." {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("`{name}` is not a plain file name"),
        ));
    }
    CString::new(name).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))
}

fn last_err() -> std::io::Error {
    std::io::Error::last_os_error()
}

fn fstat(fd: BorrowedFd<'_>) -> std::io::Result<libc::stat> {
    // SAFETY: `st` is written by the kernel; the descriptor is live for the call.
    let mut st: libc::stat = unsafe { std::mem::zeroed() };
    if unsafe { libc::fstat(fd.as_raw_fd(), &mut st) } != 0 {
        return Err(last_err());
    }
    Ok(st)
}

/// Whether group `gid` has a member other than the running user (listed in the group, or
/// with it as their primary group in the password database).
fn group_has_others(gid: u32) -> bool {
    let me = euid();
    let mut buf = vec![0u8; 16384];
    // SAFETY: getgrgid_r writes into `gr` and `buf` (its length given), both live here.
    let mut gr: libc::group = unsafe { std::mem::zeroed() };
    let mut found: *mut libc::group = std::ptr::null_mut();
    let rc =
        unsafe { libc::getgrgid_r(gid, &mut gr, buf.as_mut_ptr().cast(), buf.len(), &mut found) };
    if rc != 0 || found.is_null() {
        return true; // unknown: assume shared
    }
    let my_name = user_name(me);
    let my_name = my_name.split(' ').next().unwrap_or_default();
    let mut member = gr.gr_mem;
    // SAFETY: gr_mem is a NULL-terminated array of C strings inside `buf`.
    while !member.is_null() && !unsafe { *member }.is_null() {
        let name = unsafe { CStr::from_ptr(*member) }.to_string_lossy();
        if name != my_name {
            return true;
        }
        member = unsafe { member.add(1) };
    }
    // Users whose primary group it is.
    let Ok(passwd) = std::fs::read_to_string("/etc/passwd") else { return true };
    passwd.lines().any(|l| {
        let f: Vec<&str> = l.split(':').collect();
        f.len() > 3 && f[3].parse::<u32>() == Ok(gid) && f[2].parse::<u32>() != Ok(me)
    })
}

/// Whether `uid` is the kernel's overflow uid of a user namespace that maps only some
/// users (`unshare -r`, a rootless container): an owner outside the namespace, the host's
/// root among them, shows as it. Such a directory on the way is trusted as root's is (its
/// mode is still checked); in the initial namespace (the full map) that uid is a real user
/// (`nobody`) and is not.
fn outside_this_namespace(uid: u32) -> bool {
    // The namespace is the process's: read once.
    static OVERFLOW: std::sync::OnceLock<Option<u32>> = std::sync::OnceLock::new();
    let overflow = OVERFLOW.get_or_init(|| {
        let read = |p: &str| std::fs::read_to_string(p).unwrap_or_default();
        let overflow = read("/proc/sys/kernel/overflowuid").trim().parse::<u32>().unwrap_or(65534);
        let full_map =
            read("/proc/self/uid_map").split_whitespace().map(str::to_owned).collect::<Vec<_>>()
                == ["0", "0", "4294967295"];
        (!full_map).then_some(overflow)
    });
    *overflow == Some(uid)
}

/// What another user could do with a directory of `uid`, `gid`, `mode`, if anything: owned
/// by `owners` only, not writable by others (unless `sticky_ok` and the sticky bit is set).
fn directory_risk(uid: u32, gid: u32, mode: u32, mine_only: bool) -> Option<String> {
    let me = euid();
    let owner_ok = uid == me || (!mine_only && (uid == 0 || outside_this_namespace(uid)));
    let sticky = mode & 0o1000 != 0;
    if !owner_ok {
        let whose =
            if mine_only || me == 0 { user_name(me) } else { format!("{} or root", user_name(me)) };
        return Some(format!(
            "is owned by {} (mode {:04o}), not by {whose}",
            user_name(uid),
            mode & 0o7777
        ));
    }
    if sticky && !mine_only {
        return None;
    }
    if mode & 0o002 != 0 {
        return Some(format!(
            "has mode {:04o}: every user can write in it, and so plant links and files there",
            mode & 0o7777
        ));
    }
    if mode & 0o020 != 0 && group_has_others(gid) {
        return Some(format!(
            "has mode {:04o}: group {gid} can write in it, and that group has other members",
            mode & 0o7777
        ));
    }
    None
}

/// Checks the directories on the way to `path` (not `path` itself): each must be owned by
/// root or this user and not writable by another user, or sticky.
fn check_ancestors(path: &Path) -> Result<(), OutError> {
    let mut prefix = PathBuf::new();
    let comps: Vec<Component<'_>> = path.components().collect();
    for c in &comps[..comps.len().saturating_sub(1)] {
        prefix.push(c);
        let meta = std::fs::symlink_metadata(&prefix).map_err(|e| OutError::io(&prefix, e))?;
        if meta.file_type().is_symlink() {
            let owner = meta.uid();
            if owner != euid() && owner != 0 {
                let why = format!("is a symbolic link owned by {}", user_name(owner));
                return Err(OutError::not_yours(&prefix, why));
            }
            continue;
        }
        if let Some(why) = directory_risk(meta.uid(), meta.gid(), meta.mode(), false) {
            return Err(OutError::not_yours(&prefix, format!("(on the way to OUT) {why}")));
        }
    }
    Ok(())
}

impl OutDir {
    /// Makes OUT (and its missing parents, with the user's umask) unless it exists, then
    /// [`OutDir::open`]s it.
    pub fn make(path: &Path) -> Result<Self, OutError> {
        let abs = std::path::absolute(path).map_err(|e| OutError::io(path, e))?;
        // The deepest directory on the way that exists is checked before anything is made.
        let mut existing = abs.as_path();
        while std::fs::symlink_metadata(existing).is_err() {
            match existing.parent() {
                Some(p) => existing = p,
                None => break,
            }
        }
        if existing != abs {
            check_ancestors(&existing.join("-"))?;
            let real = std::fs::canonicalize(existing).map_err(|e| OutError::io(existing, e))?;
            check_ancestors(&real.join("-"))?;
        }
        if std::fs::symlink_metadata(&abs).is_err() {
            std::fs::create_dir_all(&abs).map_err(|e| OutError::io(&abs, e))?;
        }
        Self::open(path)
    }

    /// Opens OUT, an existing directory, refusing one that is not the user's to keep (see
    /// the module's rules).
    pub fn open(path: &Path) -> Result<Self, OutError> {
        Self::open_with(path, true)
    }

    /// Opens a directory to write one file into (a `--ready-file`, an address file): as
    /// [`OutDir::open`], but a sticky directory of root's or this user's that others may
    /// write (`/tmp`) is taken too. What [`OutDir`] makes there is safe all the same (an
    /// exclusive temporary renamed over the name, never a link followed; another user's
    /// file in a sticky directory cannot replace this user's).
    pub fn open_shared(path: &Path) -> Result<Self, OutError> {
        Self::open_with(path, false)
    }

    fn open_with(path: &Path, strict: bool) -> Result<Self, OutError> {
        let abs = std::path::absolute(path).map_err(|e| OutError::io(path, e))?;
        check_ancestors(&abs)?;
        let meta = std::fs::symlink_metadata(&abs).map_err(|e| OutError::io(&abs, e))?;
        if meta.file_type().is_symlink() && meta.uid() != euid() && meta.uid() != 0 {
            let why = format!("is a symbolic link owned by {}", user_name(meta.uid()));
            return Err(OutError::not_yours(&abs, why));
        }
        let real = std::fs::canonicalize(&abs).map_err(|e| OutError::io(&abs, e))?;
        if real != abs {
            check_ancestors(&real)?;
        }
        let c = CString::new(real.as_os_str().as_bytes()).map_err(|e| {
            OutError::io(&real, std::io::Error::new(std::io::ErrorKind::InvalidInput, e))
        })?;
        // SAFETY: a path we own; the descriptor returned is owned below.
        let fd = unsafe {
            libc::open(
                c.as_ptr(),
                libc::O_RDONLY | libc::O_DIRECTORY | libc::O_NOFOLLOW | libc::O_CLOEXEC,
            )
        };
        if fd < 0 {
            return Err(OutError::io(&real, last_err()));
        }
        // SAFETY: a fresh descriptor, ours alone.
        let fd = unsafe { OwnedFd::from_raw_fd(fd) };
        let out = Self { fd, path: path.to_path_buf() };
        out.check_self(path, strict)?;
        Ok(out)
    }

    fn check_self(&self, shown: &Path, strict: bool) -> Result<(), OutError> {
        let st = fstat(self.fd.as_fd()).map_err(|e| OutError::io(shown, e))?;
        let shared_ok = !strict && st.st_mode & 0o1000 != 0;
        match directory_risk(st.st_uid, st.st_gid, st.st_mode, !shared_ok) {
            Some(why) => Err(OutError::not_yours(shown, why)),
            None => Ok(()),
        }
    }

    /// A second descriptor of the same directory.
    pub fn try_clone(&self) -> std::io::Result<Self> {
        Ok(Self { fd: self.fd.try_clone()?, path: self.path.clone() })
    }

    /// The path OUT was opened by (for messages and for readers).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// `OUT/name` as a path (for messages and readers).
    pub fn join(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }

    /// The descriptor of OUT.
    pub fn fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }

    fn openat(&self, name: &str, flags: i32, mode: u32) -> std::io::Result<File> {
        let c = cstr(name)?;
        // SAFETY: a live directory descriptor and a NUL-terminated name.
        let fd = unsafe {
            libc::openat(
                self.fd.as_raw_fd(),
                c.as_ptr(),
                flags | libc::O_NOFOLLOW | libc::O_CLOEXEC,
                mode as libc::c_uint,
            )
        };
        if fd < 0 {
            return Err(last_err());
        }
        // SAFETY: a fresh descriptor, ours alone.
        Ok(unsafe { File::from_raw_fd(fd) })
    }

    /// Removes `OUT/name` (a file); nothing when there is none.
    pub fn remove(&self, name: &str) -> std::io::Result<()> {
        let c = cstr(name)?;
        // SAFETY: a live directory descriptor and a NUL-terminated name.
        if unsafe { libc::unlinkat(self.fd.as_raw_fd(), c.as_ptr(), 0) } != 0 {
            let e = last_err();
            if e.kind() != std::io::ErrorKind::NotFound {
                return Err(e);
            }
        }
        Ok(())
    }

    /// Creates `OUT/name` for writing as it grows, replacing whatever had that name (never
    /// through a link): mode `0666` less the umask, or `mode` with [`OutDir::create_mode`].
    pub fn create(&self, name: &str) -> std::io::Result<File> {
        self.create_mode(name, 0o666)
    }

    /// [`OutDir::create`] with `mode` (less the umask; `0600` stays `0600`).
    pub fn create_mode(&self, name: &str, mode: u32) -> std::io::Result<File> {
        for _ in 0..3 {
            self.remove(name)?;
            let flags = libc::O_WRONLY | libc::O_CREAT | libc::O_EXCL;
            match self.openat(name, flags, mode) {
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                other => return other,
            }
        }
        Err(std::io::Error::other(format!("{} keeps reappearing", self.join(name).display())))
    }

    /// Opens `OUT/name` to append (made if missing), never through a link, and only a
    /// regular file of this user's.
    pub fn append(&self, name: &str) -> std::io::Result<File> {
        let f = self.openat(name, libc::O_WRONLY | libc::O_APPEND | libc::O_CREAT, 0o666)?;
        let st = fstat(f.as_fd())?;
        if st.st_mode & libc::S_IFMT != libc::S_IFREG || st.st_uid != euid() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::PermissionDenied,
                format!(
                    "{} is not a regular file of {}",
                    self.join(name).display(),
                    user_name(euid())
                ),
            ));
        }
        Ok(f)
    }

    /// A temporary for `OUT/name`, renamed into place by [`Atomic::commit`] and removed if
    /// dropped before: mode `0666` less the umask.
    pub fn atomic(&self, name: &str) -> std::io::Result<Atomic> {
        self.atomic_mode(name, 0o666)
    }

    /// [`OutDir::atomic`] with `mode` (less the umask).
    pub fn atomic_mode(&self, name: &str, mode: u32) -> std::io::Result<Atomic> {
        cstr(name)?;
        for _ in 0..8 {
            let tmp = format!(".{name}.{}.partial", crate::private::random_name(8));
            let flags = libc::O_WRONLY | libc::O_CREAT | libc::O_EXCL;
            match self.openat(&tmp, flags, mode) {
                Ok(file) => {
                    let dir = self.try_clone()?;
                    return Ok(Atomic { dir, file: Some(file), tmp, name: name.to_owned() });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(e),
            }
        }
        Err(std::io::Error::other("no free temporary name"))
    }

    /// Writes `bytes` to `OUT/name` whole or not at all.
    pub fn write(&self, name: &str, bytes: &[u8]) -> std::io::Result<()> {
        let mut a = self.atomic(name)?;
        a.write_all(bytes)?;
        a.commit()
    }

    /// Makes (`mkdirat`, mode `0777` less the umask, or `mode`) or opens subdirectory
    /// `OUT/name`, never through a link, refused like OUT when it is not this user's alone.
    pub fn subdir(&self, name: &str) -> Result<OutDir, OutError> {
        self.subdir_mode(name, 0o777)
    }

    /// [`OutDir::subdir`] made with `mode` (less the umask) when new.
    pub fn subdir_mode(&self, name: &str, mode: u32) -> Result<OutDir, OutError> {
        let path = self.join(name);
        let c = cstr(name).map_err(|e| OutError::io(&path, e))?;
        // SAFETY: a live directory descriptor and a NUL-terminated name.
        if unsafe { libc::mkdirat(self.fd.as_raw_fd(), c.as_ptr(), mode as libc::mode_t) } != 0 {
            let e = last_err();
            if e.kind() != std::io::ErrorKind::AlreadyExists {
                return Err(OutError::io(&path, e));
            }
        }
        // SAFETY: as above.
        let fd = unsafe {
            libc::openat(
                self.fd.as_raw_fd(),
                c.as_ptr(),
                libc::O_RDONLY | libc::O_DIRECTORY | libc::O_NOFOLLOW | libc::O_CLOEXEC,
            )
        };
        if fd < 0 {
            let e = last_err();
            if e.raw_os_error() == Some(libc::ELOOP) || e.raw_os_error() == Some(libc::ENOTDIR) {
                let why = match std::fs::symlink_metadata(&path) {
                    Ok(m) => format!(
                        "is not a directory but a {:?}, owned by {}",
                        m.file_type(),
                        user_name(m.uid())
                    ),
                    Err(_) => "is not a directory".to_owned(),
                };
                return Err(OutError::not_yours(&path, why));
            }
            return Err(OutError::io(&path, e));
        }
        // SAFETY: a fresh descriptor, ours alone.
        let sub = OutDir { fd: unsafe { OwnedFd::from_raw_fd(fd) }, path: path.clone() };
        sub.check_self(&path, true)?;
        Ok(sub)
    }
}

/// A file of OUT being written: a temporary until [`Atomic::commit`] renames it into place;
/// removed if dropped before.
#[derive(Debug)]
pub struct Atomic {
    dir: OutDir,
    file: Option<File>,
    tmp: String,
    name: String,
}

impl Atomic {
    /// The open temporary.
    pub fn file(&mut self) -> &mut File {
        self.file.as_mut().expect("open until committed")
    }

    /// Flushes and renames the temporary into place (`renameat`).
    pub fn commit(mut self) -> std::io::Result<()> {
        let file = self.file.take().expect("open until committed");
        drop(file);
        let (from, to) = (cstr(&self.tmp)?, cstr(&self.name)?);
        let fd = self.dir.fd.as_raw_fd();
        // SAFETY: a live directory descriptor and NUL-terminated names.
        if unsafe { libc::renameat(fd, from.as_ptr(), fd, to.as_ptr()) } != 0 {
            return Err(last_err()); // the temporary is removed by drop
        }
        self.tmp.clear();
        Ok(())
    }
}

impl Write for Atomic {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.file().write(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.file().flush()
    }
}

impl std::io::Seek for Atomic {
    fn seek(&mut self, pos: std::io::SeekFrom) -> std::io::Result<u64> {
        self.file().seek(pos)
    }
}

impl Drop for Atomic {
    fn drop(&mut self) {
        if !self.tmp.is_empty() {
            let _ = self.dir.remove(&self.tmp);
        }
    }
}

/// Writes `bytes` to file `path` whole or not at all, through [`OutDir`] on its directory
/// (checked as OUT): the drop-in for `std::fs::write` into a run's directory.
pub fn write_file(path: &Path, bytes: impl AsRef<[u8]>) -> std::io::Result<()> {
    let (dir, name) = split(path)?;
    OutDir::open_shared(dir).map_err(to_io)?.write(name, bytes.as_ref())
}

/// Creates file `path` to write as it grows ([`OutDir::create`] on its directory, checked
/// as OUT): the drop-in for `std::fs::File::create` into a run's directory.
pub fn create_file(path: &Path) -> std::io::Result<File> {
    let (dir, name) = split(path)?;
    OutDir::open_shared(dir).map_err(to_io)?.create(name)
}

/// Opens file `path` to append ([`OutDir::append`] on its directory, checked as OUT).
pub fn append_file(path: &Path) -> std::io::Result<File> {
    let (dir, name) = split(path)?;
    OutDir::open_shared(dir).map_err(to_io)?.append(name)
}

/// An [`OutError`] as an I/O error (its message kept).
pub fn to_io(e: OutError) -> std::io::Error {
    match e {
        OutError::Io { source, .. } => source,
        e @ OutError::NotYours { .. } => {
            std::io::Error::new(std::io::ErrorKind::PermissionDenied, e.to_string())
        }
    }
}

/// The directory and file name of `path`.
pub fn split(path: &Path) -> std::io::Result<(&Path, &str)> {
    let name = path.file_name().and_then(|n| n.to_str()).ok_or_else(|| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{} names no file", path.display()),
        )
    })?;
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    Ok((dir, name))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::PermissionsExt;

    fn scratch(name: &str) -> PathBuf {
        crate::private::tests::scratch(&format!("outdir-{name}"))
    }

    #[test]
    fn files_in_out_are_never_written_through_links_and_temporaries_never_stay() {
        let d = scratch("links");
        let target = d.join("target");
        std::fs::write(&target, b"keep").expect("target");
        let out = OutDir::make(&d.join("out")).expect("out");
        for name in ["a.csv", "b.json", "c.log"] {
            std::os::unix::fs::symlink(&target, d.join("out").join(name)).expect("link");
        }
        out.write("a.csv", b"new").expect("write");
        drop(out.create("b.json").expect("create"));
        assert!(out.append("c.log").is_err(), "appended through a link");
        assert_eq!(std::fs::read(&target).expect("target"), b"keep");
        assert_eq!(std::fs::read(d.join("out/a.csv")).expect("a"), b"new");
        {
            let mut a = out.atomic("d.json").expect("atomic");
            a.write_all(b"half").expect("write");
        } // dropped, not committed
        let left: Vec<_> = std::fs::read_dir(d.join("out"))
            .expect("read")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains("partial") || n == "d.json")
            .collect();
        assert!(left.is_empty(), "{left:?}");
        std::os::unix::fs::symlink(&d, d.join("out/sub")).expect("link");
        assert!(out.subdir("sub").is_err_and(|e| e.is_refusal()));
        let sub = out.subdir("flight").expect("subdir");
        sub.write("x", b"y").expect("write in subdir");
        std::fs::remove_dir_all(&d).expect("clean");
    }

    #[test]
    fn an_out_others_can_write_is_refused_naming_its_mode() {
        let d = scratch("mode");
        std::fs::create_dir(d.join("open")).expect("dir");
        std::fs::set_permissions(d.join("open"), std::fs::Permissions::from_mode(0o777))
            .expect("chmod");
        let e = OutDir::open(&d.join("open")).expect_err("refused");
        assert!(e.is_refusal() && e.to_string().contains("0777"), "{e}");
        // Below a directory others can write (not sticky): refused too.
        let e = OutDir::make(&d.join("open/run")).expect_err("refused");
        assert!(e.is_refusal() && e.to_string().contains("on the way"), "{e}");
        std::fs::remove_dir_all(&d).expect("clean");
    }
}
