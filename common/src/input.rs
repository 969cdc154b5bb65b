//! What a command line names, checked before anything starts: a file given as input is a
//! regular file of bounded size (a FIFO or a device would block or never end, a huge file
//! would be read whole), read as text with the line and column of any byte that is not
//! UTF-8; an output directory is one this user can make or write into; a number is in the
//! range its flag's help states ([`number_in`], a clap value parser).
//!
//! Every refusal here is the user's to mend: the commands turn it into exit code 2
//! (`docs/running.md`, "Exit codes").

use std::fmt;
use std::io::Read;
use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
use std::path::Path;

/// Why a file named on the command line cannot be read as input.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    /// No such file.
    #[error("no such file")]
    Missing,
    /// Something other than a regular file (a FIFO, a device, a directory, a socket).
    #[error("{0}, not a regular file")]
    NotRegular(&'static str),
    /// Larger than this kind of input can be.
    #[error("{size} bytes, more than the {max} bytes such a file can hold")]
    TooLarge {
        /// The file's size.
        size: u64,
        /// The largest allowed.
        max: u64,
    },
    /// A byte that is not UTF-8, where text is expected.
    #[error(
        "line {line}, column {column}: byte 0x{byte:02x} is not UTF-8 (the file must be UTF-8 text)"
    )]
    NotUtf8 {
        /// 1-based line of the first bad byte.
        line: usize,
        /// 1-based column (characters) of the first bad byte.
        column: usize,
        /// The byte.
        byte: u8,
    },
    /// The read failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

/// What a file type is, in words.
fn kind(t: std::fs::FileType) -> &'static str {
    if t.is_file() {
        "a file"
    } else if t.is_dir() {
        "a directory"
    } else if t.is_fifo() {
        "a FIFO"
    } else if t.is_char_device() || t.is_block_device() {
        "a device"
    } else if t.is_socket() {
        "a socket"
    } else {
        "not a file"
    }
}

/// The bytes of the regular file `path`, at most `max` of them. Opened without blocking
/// (a FIFO named by mistake is refused, not waited on) and checked on the open file, so a
/// file swapped between a check and the open is refused too.
pub fn read_bytes(path: &Path, max: u64) -> Result<Vec<u8>, InputError> {
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY)
        .open(path)
        .map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => InputError::Missing,
            _ => InputError::Io(e),
        })?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(InputError::NotRegular(kind(meta.file_type())));
    }
    if meta.len() > max {
        return Err(InputError::TooLarge { size: meta.len(), max });
    }
    let mut bytes = Vec::with_capacity(usize::try_from(meta.len()).unwrap_or(0));
    // A file growing while read stops at the bound all the same.
    file.take(max + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max {
        return Err(InputError::TooLarge { size: bytes.len() as u64, max });
    }
    Ok(bytes)
}

/// The UTF-8 text of the regular file `path`, at most `max` bytes ([`read_bytes`]).
pub fn read_text(path: &Path, max: u64) -> Result<String, InputError> {
    text(read_bytes(path, max)?)
}

/// `bytes` as UTF-8, or where the first byte that is not.
pub fn text(bytes: Vec<u8>) -> Result<String, InputError> {
    String::from_utf8(bytes).map_err(|e| {
        let at = e.utf8_error().valid_up_to();
        let bytes = e.as_bytes();
        let good = std::str::from_utf8(&bytes[..at]).unwrap_or_default();
        let line_start = good.rfind('\n').map_or(0, |i| i + 1);
        InputError::NotUtf8 {
            line: good.matches('\n').count() + 1,
            column: good[line_start..].chars().count() + 1,
            byte: bytes[at],
        }
    })
}

/// Whether `out` can be the output directory: an existing directory this user may write
/// into, or a path whose nearest existing ancestor is one (the command makes the rest).
/// Nothing is left here (a probe directory is made and removed at once), so a command
/// refused later leaves nothing behind.
pub fn check_out_dir(out: &Path) -> Result<(), String> {
    let mut at = out;
    loop {
        match std::fs::metadata(at) {
            Ok(m) if m.is_dir() => break,
            Ok(m) => {
                return Err(format!(
                    "{} is {}, not a directory",
                    at.display(),
                    kind(m.file_type())
                ));
            }
            // A missing path, or one under a file (`/etc/passwd/x`): its parent says which.
            Err(e)
                if e.kind() == std::io::ErrorKind::NotFound
                    || e.raw_os_error() == Some(libc::ENOTDIR) => {}
            Err(e) => return Err(format!("{}: {e}", at.display())),
        }
        at = match at.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
    }
    let c = std::ffi::CString::new(at.as_os_str().as_encoded_bytes())
        .map_err(|_| format!("{} has a NUL byte", out.display()))?;
    // SAFETY: `c` is a valid NUL-terminated path for the call's duration.
    if unsafe { libc::access(c.as_ptr(), libc::W_OK | libc::X_OK) } != 0 {
        let e = std::io::Error::last_os_error();
        let what = if at == out { "it" } else { "its nearest existing directory" };
        return Err(format!("{what}, {}, is not writable by this user: {e}", at.display()));
    }
    // `access` lets root through where nothing can be made (a read-only or kernel file
    // system such as /proc, an immutable directory): make and remove a directory there.
    let probe = at.join(format!(".rotorloop-probe-{}", crate::private::random_name(12)));
    match std::fs::create_dir(&probe) {
        Ok(()) => {
            let _ = std::fs::remove_dir(&probe);
            Ok(())
        }
        Err(e) => {
            let what = if at == out { "it" } else { "its nearest existing directory" };
            Err(format!("{what}, {}, takes no new directory: {e}", at.display()))
        }
    }
}

/// A clap value parser for a directory a command writes into: [`check_out_dir`]'s.
pub fn dir_to_write(s: &str) -> Result<std::path::PathBuf, String> {
    let p = std::path::PathBuf::from(s);
    check_out_dir(&p).map(|()| p)
}

/// A clap value parser for an `f64` flag: a finite number from `lo` to `hi` (`unit` says
/// what it is), as the flag's help states.
pub fn number_in(
    lo: f64,
    hi: f64,
    unit: &'static str,
) -> impl Fn(&str) -> Result<f64, RangeError> + Clone + Send + Sync + 'static {
    move |s: &str| match s.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v >= lo && v <= hi => Ok(v),
        _ => Err(RangeError { range: format!("a finite number from {lo} to {hi} ({unit})") }),
    }
}

/// A clap value parser for an integer flag: a whole number from `lo` to `hi` (`unit` says
/// what it is), as the flag's help states. Unlike clap's own ranged parsers,
/// a negative or malformed value gets the range too, not "invalid digit".
pub fn whole_in<T>(
    lo: T,
    hi: T,
    unit: &'static str,
) -> impl Fn(&str) -> Result<T, RangeError> + Clone + Send + Sync + 'static
where
    T: std::str::FromStr + PartialOrd + fmt::Display + Copy + Send + Sync + 'static,
{
    move |s: &str| match s.trim().parse::<T>() {
        Ok(v) if v >= lo && v <= hi => Ok(v),
        _ => Err(RangeError { range: format!("a whole number from {lo} to {hi} ({unit})") }),
    }
}

/// A number outside its flag's range (clap names the flag and the value).
#[derive(Debug, Clone)]
pub struct RangeError {
    range: String,
}

impl fmt::Display for RangeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "allowed: {}", self.range)
    }
}

impl std::error::Error for RangeError {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fifo_is_refused_without_blocking() {
        let dir = std::env::temp_dir().join(format!("rl-input-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let fifo = dir.join("fifo");
        let c = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).expect("path");
        // SAFETY: a valid path for the call.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0, "mkfifo");
        let e = read_bytes(&fifo, 1024).expect_err("a FIFO");
        assert!(e.to_string().contains("a FIFO, not a regular file"), "{e}");
        let e = read_bytes(&dir, 1024).expect_err("a directory");
        assert!(e.to_string().contains("a directory"), "{e}");
        let big = dir.join("big");
        std::fs::write(&big, vec![b'x'; 2000]).expect("write");
        let e = read_bytes(&big, 1024).expect_err("too large");
        assert!(e.to_string().contains("2000 bytes, more than the 1024"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn an_out_where_nothing_can_be_made_is_refused_and_left_as_it_was() {
        let dir = std::env::temp_dir().join(format!("rl-out-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        assert_eq!(check_out_dir(&dir.join("a/b")), Ok(()));
        assert_eq!(std::fs::read_dir(&dir).expect("read").count(), 0, "the probe is removed");
        let _ = std::fs::remove_dir_all(&dir);
        // /proc lets root through `access`, but takes no directory.
        if Path::new("/proc/self").exists() {
            let e = check_out_dir(Path::new("/proc/rotorloop-out")).expect_err("/proc");
            assert!(e.contains("directory, /proc, "), "{e}");
        } else {
            eprintln!("skipped the /proc half: no /proc here");
        }
    }

    #[test]
    fn the_first_byte_that_is_not_utf8_is_located() {
        let e = text(b"a = 1\nbb = \"\xff\"\n".to_vec()).expect_err("not UTF-8");
        assert_eq!(
            e.to_string(),
            "line 2, column 7: byte 0xff is not UTF-8 (the file must be UTF-8 text)"
        );
    }

    #[test]
    fn numbers_outside_the_range_and_not_finite_are_refused() {
        let p = number_in(0.0, 10.0, "seconds");
        assert_eq!(p("2.5").ok(), Some(2.5));
        assert_eq!(p("-0").ok(), Some(0.0));
        for bad in ["-1", "nan", "inf", "1e300", "x", ""] {
            let e = p(bad).expect_err(bad).to_string();
            assert_eq!(e, "allowed: a finite number from 0 to 10 (seconds)");
        }
        let w = whole_in(512u64, 1 << 24, "ticks");
        assert_eq!(w("512").ok(), Some(512));
        for bad in ["-1", "511", "16777217", "18446744073709551615", "1.5", "x"] {
            let e = w(bad).expect_err(bad).to_string();
            assert_eq!(e, "allowed: a whole number from 512 to 16777216 (ticks)");
        }
    }
}
