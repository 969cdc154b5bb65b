//! What a run makes in places every user can write (`/dev/shm`): made by the run,
//! exclusively and privately, and never another user's followed, reused or deleted.
//!
//! A directory is made with `mkdir` (mode 0700), a file with `O_CREAT | O_EXCL |
//! O_NOFOLLOW` (mode 0600), whatever the umask. What is already there is used only when it
//! is this user's, not a symbolic link, and private (`lstat`/`fstat`: owner, type, no
//! group or other bits); anything else is refused with [`Foreign`], which names the path,
//! its owner and mode and what to do. `/dev/shm` is sticky (mode 1777): a name made by
//! this user there cannot be removed or replaced by another, so checking it once holds.

use std::fs::{File, Metadata};
use std::os::unix::fs::{DirBuilderExt, MetadataExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

/// Something already at a path a run makes for itself, which is not the run's user's
/// own private file or directory: refused (exit 2), never used.
#[derive(Debug, thiserror::Error)]
#[error(
    "{path} {why}; a run uses only what its own user made there, privately. Remove it (its \
     owner or root can: `rm -r {path}`), or choose another --domain",
    path = .path.display()
)]
pub struct Foreign {
    /// The path.
    pub path: PathBuf,
    /// What is wrong with it, in words (owner, type, mode).
    pub why: String,
}

/// A failure to make or open a private path: refused ([`Foreign`]), or the system's error.
#[derive(Debug, thiserror::Error)]
pub enum PrivateError {
    /// Already there, and not this user's private file or directory.
    #[error(transparent)]
    Foreign(#[from] Foreign),
    /// The system refused.
    #[error("{}: {source}", .path.display())]
    Io {
        /// The path.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
}

impl PrivateError {
    fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io { path: path.to_path_buf(), source }
    }
}

/// Maps `len` bytes of `file` shared, to read and write (`flags`: `MAP_` flags beside
/// `MAP_SHARED`); the system's error where it cannot.
pub fn map_shared(file: &File, len: usize, flags: libc::c_int) -> std::io::Result<*mut u8> {
    use std::os::fd::AsRawFd;
    let (prot, fd) = (libc::PROT_READ | libc::PROT_WRITE, file.as_raw_fd());
    // SAFETY: a new mapping of an open descriptor; the kernel checks the length and mode.
    let map =
        unsafe { libc::mmap(std::ptr::null_mut(), len, prot, libc::MAP_SHARED | flags, fd, 0) };
    match map == libc::MAP_FAILED {
        true => Err(std::io::Error::last_os_error()),
        false => Ok(map.cast()),
    }
}

/// The effective user id of this process.
pub fn euid() -> u32 {
    // SAFETY: a plain getter.
    unsafe { libc::geteuid() }
}

/// `uid`'s login name, or its number.
pub fn user_name(uid: u32) -> String {
    let mut buf = vec![0u8; 4096];
    // SAFETY: getpwuid_r writes into `pw` and `buf` (its length given), both live here.
    let mut pw: libc::passwd = unsafe { std::mem::zeroed() };
    let mut found: *mut libc::passwd = std::ptr::null_mut();
    let rc =
        unsafe { libc::getpwuid_r(uid, &mut pw, buf.as_mut_ptr().cast(), buf.len(), &mut found) };
    if rc != 0 || found.is_null() || pw.pw_name.is_null() {
        return format!("uid {uid}");
    }
    // SAFETY: pw_name points into `buf`, NUL-terminated by getpwuid_r.
    let name = unsafe { std::ffi::CStr::from_ptr(pw.pw_name) };
    format!("{} (uid {uid})", name.to_string_lossy())
}

/// Whether `meta` (from `lstat` or `fstat`) is this user's own private directory (`dir`)
/// or regular file; else why not.
pub fn check(path: &Path, meta: &Metadata, dir: bool) -> Result<(), Foreign> {
    let ft = meta.file_type();
    let kind = if ft.is_symlink() {
        Some("a symbolic link")
    } else if dir && !ft.is_dir() {
        Some("not a directory")
    } else if !dir && !ft.is_file() {
        Some("not a regular file")
    } else {
        None
    };
    let foreign = |why: String| Foreign { path: path.to_path_buf(), why };
    if let Some(kind) = kind {
        return Err(foreign(format!("is {kind} (owned by {})", user_name(meta.uid()))));
    }
    if meta.uid() != euid() {
        let (owner, me) = (user_name(meta.uid()), user_name(euid()));
        return Err(foreign(format!("already exists, owned by {owner}, not by {me}")));
    }
    let mode = meta.mode() & 0o7777;
    if mode & 0o077 != 0 {
        return Err(foreign(format!(
            "already exists with mode {mode:04o}: others may have opened it (a run's own are \
             {})",
            if dir { "0700" } else { "0600" }
        )));
    }
    Ok(())
}

/// Makes directory `path` (mode 0700), or uses it if it is already this user's own
/// private directory. A directory of this user's with group or other bits (made by an
/// older build) is made private: only its own user could have put anything in it.
/// The parent must exist. A trailing `/` is dropped (with it the system would follow a
/// link in the directory's place).
pub fn dir(path: &Path) -> Result<(), PrivateError> {
    use std::os::unix::ffi::OsStrExt;
    let bytes = path.as_os_str().as_bytes();
    let end = bytes.iter().rposition(|&b| b != b'/').map_or(bytes.len().min(1), |i| i + 1);
    let path = Path::new(std::ffi::OsStr::from_bytes(&bytes[..end]));
    match std::fs::DirBuilder::new().mode(0o700).create(path) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
        Err(e) => return Err(PrivateError::io(path, e)),
    }
    let meta = std::fs::symlink_metadata(path).map_err(|e| PrivateError::io(path, e))?;
    match check(path, &meta, true) {
        Ok(()) => Ok(()),
        Err(_) if meta.is_dir() && meta.uid() == euid() && !meta.file_type().is_symlink() => {
            // Ours (a umask that took the owner's bits, or an older build's 0755): only
            // this user could have written in it.
            std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o700))
                .map_err(|e| PrivateError::io(path, e))
        }
        Err(f) => Err(f.into()),
    }
}

/// Creates file `path` exclusively (`O_EXCL | O_NOFOLLOW`, mode 0600 whatever the
/// umask), read and write. `Ok(None)` when something is already there.
pub fn create_file(path: &Path) -> Result<Option<File>, PrivateError> {
    let opened = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create_new(true)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path);
    match opened {
        Ok(f) => {
            // The umask may have taken bits of 0600; the descriptor is ours alone.
            f.set_permissions(std::fs::Permissions::from_mode(0o600))
                .map_err(|e| PrivateError::io(path, e))?;
            Ok(Some(f))
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(None),
        Err(e) => Err(PrivateError::io(path, e)),
    }
}

/// Opens file `path` read and write if it is this user's own private regular file (never
/// through a link): `Ok(None)` when there is none.
pub fn open_file(path: &Path) -> Result<Option<File>, PrivateError> {
    let opened = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC | libc::O_NONBLOCK)
        .open(path);
    let file = match opened {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        // O_NOFOLLOW on a link: ELOOP. Anything we may not open: say whose it is.
        Err(e) => {
            return match std::fs::symlink_metadata(path) {
                Ok(meta) => Err(check(path, &meta, false)
                    .err()
                    .map_or_else(|| PrivateError::io(path, e), PrivateError::Foreign)),
                Err(_) => Err(PrivateError::io(path, e)),
            };
        }
    };
    let meta = file.metadata().map_err(|e| PrivateError::io(path, e))?;
    check(path, &meta, false)?;
    Ok(Some(file))
}

/// Creates file `path` privately ([`create_file`]) or opens this user's own private file
/// there ([`open_file`]); `true` with a file it created.
pub fn open_or_create_file(path: &Path) -> Result<(File, bool), PrivateError> {
    // A file removed between the two attempts (a domain's clean-up) is created again.
    for _ in 0..3 {
        if let Some(f) = create_file(path)? {
            return Ok((f, true));
        }
        if let Some(f) = open_file(path)? {
            return Ok((f, false));
        }
    }
    Err(PrivateError::io(path, std::io::Error::other("it keeps appearing and disappearing")))
}

/// Writes `bytes` to a new private file `path` (exclusively; refused when anything is
/// there).
pub fn write_new(path: &Path, bytes: &[u8]) -> Result<(), PrivateError> {
    use std::io::Write;
    let Some(mut f) = create_file(path)? else {
        let meta = std::fs::symlink_metadata(path).map_err(|e| PrivateError::io(path, e))?;
        let why =
            check(path, &meta, false).err().map_or_else(|| "already exists".to_owned(), |f| f.why);
        return Err(Foreign { path: path.to_path_buf(), why }.into());
    };
    f.write_all(bytes).map_err(|e| PrivateError::io(path, e))
}

/// Below this many free bytes `/dev/shm` counts as full for [`shm_full`] when the space a
/// run needs there is not known: less than one iceoryx2 node's files and a resume slot.
pub const SHM_NEARLY_FULL: u64 = 1 << 20;

/// What to say when `/dev/shm` cannot hold what a run needs there (`need` bytes, its
/// flight rings while it runs, when known): `None` while it has room. A full `/dev/shm`
/// (another user may have filled it) makes a role die of SIGBUS on a page of a mapped
/// file, and iceoryx2 refuse a node with an `InternalError` that names nothing.
pub fn shm_full(need: Option<u64>) -> Option<String> {
    let c = c"/dev/shm";
    // SAFETY: statvfs fills the struct from a NUL-terminated path; checked for failure.
    let st = unsafe {
        let mut st: libc::statvfs = std::mem::zeroed();
        (libc::statvfs(c.as_ptr(), &mut st) == 0).then_some(st)
    }?;
    let free = st.f_bavail.saturating_mul(st.f_frsize);
    let total = st.f_blocks.saturating_mul(st.f_frsize);
    let mib = |b: u64| b as f64 / (1u64 << 20) as f64;
    let needed = need.map_or(SHM_NEARLY_FULL, |n| n.max(SHM_NEARLY_FULL));
    (free < needed).then(|| {
        let what = match need {
            Some(n) => format!("the run needs about {:.1} MiB there (its flight rings) and iceoryx2's segments", mib(n)),
            None => format!("a role needs at least {:.1} MiB there for its shared memory", mib(SHM_NEARLY_FULL)),
        };
        format!(
            "/dev/shm is full: {:.1} MiB free of {:.1} MiB; {what}. Free space there (`df -h              /dev/shm`; `ls -la /dev/shm` shows whose files take it)",
            mib(free),
            mib(total)
        )
    })
}

/// `N` bytes from the kernel's randomness (`getrandom(2)`, which blocks only until the
/// kernel's pool was first seeded at boot).
pub fn random_bytes<const N: usize>() -> std::io::Result<[u8; N]> {
    let mut buf = [0u8; N];
    let mut filled = 0;
    while filled < N {
        let rest = &mut buf[filled..];
        // SAFETY: the kernel writes at most `rest.len()` bytes into memory we own.
        let n = unsafe { libc::getrandom(rest.as_mut_ptr().cast(), rest.len(), 0) };
        match usize::try_from(n) {
            Ok(n) => filled += n,
            Err(_) => {
                let e = std::io::Error::last_os_error();
                if e.kind() != std::io::ErrorKind::Interrupted {
                    return Err(e);
                }
            }
        }
    }
    Ok(buf)
}

/// `bytes` in lowercase hex, two digits each (a secret or a nonce written as text).
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Random characters from `a-z 0-9` ([`random_bytes`]), for names another user cannot
/// guess.
pub fn random_name(len: usize) -> String {
    const ALPHABET: &[u8] = b"abcdefghijklmnopqrstuvwxyz0123456789";
    let mut out = String::with_capacity(len);
    while out.len() < len {
        let bytes = random_bytes::<16>().expect("getrandom(2) failed");
        // 252 = 7 × 36: the bytes above would bias the draw towards the first letters.
        let fair = bytes.into_iter().filter(|&b| b < 252).take(len - out.len());
        out.extend(fair.map(|b| ALPHABET[usize::from(b % 36)] as char));
    }
    out
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A fresh directory of this process's for a test (0755, whatever was there removed).
    pub(crate) fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("rl-private-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir(&d).expect("scratch");
        std::fs::set_permissions(&d, std::fs::Permissions::from_mode(0o755)).expect("chmod");
        d
    }

    #[test]
    fn a_file_is_made_0600_whatever_the_umask_and_a_link_is_never_followed() {
        let d = scratch("file");
        // SAFETY: plain setter; the old mask is put back below.
        let old = unsafe { libc::umask(0) };
        let made = create_file(&d.join("a")).expect("create").expect("new");
        unsafe { libc::umask(old) };
        assert_eq!(made.metadata().expect("meta").mode() & 0o777, 0o600);
        assert!(create_file(&d.join("a")).expect("second").is_none(), "exclusive");
        assert!(open_file(&d.join("a")).expect("open").is_some());

        let target = d.join("target");
        std::fs::write(&target, b"keep").expect("target");
        std::fs::set_permissions(&target, std::fs::Permissions::from_mode(0o600)).expect("chmod");
        std::os::unix::fs::symlink(&target, d.join("link")).expect("link");
        assert!(create_file(&d.join("link")).expect("no follow").is_none());
        match open_file(&d.join("link")) {
            Err(PrivateError::Foreign(f)) => assert!(f.why.contains("symbolic link"), "{f}"),
            other => panic!("a link was opened: {other:?}"),
        }
        match write_new(&d.join("link"), b"overwritten") {
            Err(PrivateError::Foreign(f)) => assert!(f.to_string().contains("link"), "{f}"),
            other => panic!("written through a link: {other:?}"),
        }
        assert_eq!(std::fs::read(&target).expect("target"), b"keep");

        std::fs::set_permissions(d.join("a"), std::fs::Permissions::from_mode(0o644))
            .expect("chmod");
        match open_file(&d.join("a")) {
            Err(PrivateError::Foreign(f)) => assert!(f.why.contains("0644"), "{f}"),
            other => panic!("a file others could open was used: {other:?}"),
        }
        std::fs::remove_dir_all(&d).expect("clean");
    }

    #[test]
    fn a_directory_is_made_0700_and_a_link_in_its_place_is_refused() {
        let d = scratch("dir");
        dir(&d.join("private")).expect("dir");
        let mode = std::fs::metadata(d.join("private")).expect("meta").mode() & 0o777;
        assert_eq!(mode, 0o700);
        dir(&d.join("private")).expect("ours again");
        std::os::unix::fs::symlink(&d, d.join("link")).expect("link");
        for link in [d.join("link"), d.join("link/")] {
            match dir(&link) {
                Err(PrivateError::Foreign(f)) => assert!(f.why.contains("symbolic link"), "{f}"),
                other => panic!("a link was taken for a directory: {other:?}"),
            }
        }
        let mode = std::fs::metadata(&d).expect("meta").permissions().mode() & 0o777;
        assert_eq!(mode, 0o755, "the link's target was changed");
        std::fs::remove_dir_all(&d).expect("clean");
    }

    #[test]
    fn random_names_use_the_alphabet_and_differ() {
        let (a, b) = (random_name(12), random_name(12));
        assert_eq!(a.len(), 12);
        assert!(a.bytes().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit()), "{a}");
        assert_ne!(a, b);
    }
}
