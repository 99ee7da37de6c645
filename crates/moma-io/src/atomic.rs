//! Atomic file output: every writer of this crate goes through [`atomic_write`].

use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};

use crate::error::{IoError, Result};

/// The temporary files [`atomic_write`] has open, so that a program ended by a signal can
/// remove them first ([`remove_temporaries_in_flight`]): a temporary file is removed when its
/// writer returns or unwinds, but a signal's default action ends the process without either.
static IN_FLIGHT: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// The registry, whatever a thread that panicked while holding it left (a list of paths is
/// consistent after any push or removal).
fn in_flight() -> MutexGuard<'static, Vec<PathBuf>> {
    IN_FLIGHT.lock().unwrap_or_else(|e| e.into_inner())
}

/// One registered temporary file; leaves the registry when released or dropped (written,
/// renamed or failed).
struct Registered(Option<PathBuf>);

impl Registered {
    /// Adds `path` to the registry whose lock the caller holds.
    fn push(list: &mut Vec<PathBuf>, path: &Path) -> Self {
        list.push(path.to_path_buf());
        Self(Some(path.to_path_buf()))
    }

    /// Leaves the registry whose lock the caller holds.
    fn release(mut self, list: &mut Vec<PathBuf>) {
        if let Some(path) = self.0.take() {
            forget(list, &path);
        }
    }
}

impl Drop for Registered {
    fn drop(&mut self) {
        if let Some(path) = self.0.take() {
            forget(&mut in_flight(), &path);
        }
    }
}

/// Removes one entry of `path` from the registry.
fn forget(list: &mut Vec<PathBuf>, path: &Path) {
    if let Some(i) = list.iter().position(|p| p == path) {
        list.swap_remove(i);
    }
}

/// Removes every temporary file an [`atomic_write`] has open in this process and returns the
/// registry still locked: no writer can register, rename or finish another until the guard
/// is dropped, so a program about to end on a signal holds it until it ends. The writers'
/// destination files are untouched (the old file, or none). Returns how many were removed,
/// with the guard.
///
/// For signal handling in a program's own thread (not in a signal handler: it locks and
/// allocates), as `moma`'s binary does for SIGINT, SIGTERM and SIGHUP.
pub fn remove_temporaries_in_flight() -> (usize, MutexGuard<'static, Vec<PathBuf>>) {
    let list = in_flight();
    let removed = list
        .iter()
        .filter(|p| std::fs::remove_file(p).is_ok())
        .count();
    (removed, list)
}

/// Writes `path` atomically: `write` fills a temporary file created in the destination
/// directory (named `.NAME.XXXXXX.tmp`), which is renamed over `path` only after `write` and
/// the final flush succeed. Readers therefore see either the old file or the complete new one;
/// on any error the temporary file is removed and `path` is left untouched.
///
/// The returned value of `write` is passed through. The file gets mode `0666` minus the
/// process umask on Unix (like an ordinary `File::create`), not the `0600` of a temporary
/// file. No `fsync` is issued (the rename protects against crashes of this process, not
/// against power loss).
///
/// # Errors
/// [`IoError::Invalid`] when `path` has no file name or its directory does not exist;
/// [`IoError::Io`] when the temporary file cannot be created (e.g. directory not writable),
/// written or renamed; any error returned by `write`.
///
/// # Example
/// ```
/// use std::io::Write;
/// let dir = tempfile::tempdir().unwrap();
/// let path = dir.path().join("hello.txt");
/// moma_io::atomic_write(&path, |w| {
///     w.write_all(b"hello").map_err(|e| moma_io::IoError::Io {
///         path: "hello.txt".into(),
///         action: "write",
///         source: e,
///     })
/// })
/// .unwrap();
/// assert_eq!(std::fs::read(&path).unwrap(), b"hello");
/// ```
pub fn atomic_write<T>(
    path: impl AsRef<Path>,
    write: impl FnOnce(&mut dyn Write) -> Result<T>,
) -> Result<T> {
    let path = path.as_ref();
    let Some(name) = path.file_name() else {
        return Err(IoError::invalid(path, "output path has no file name"));
    };
    let dir = folder_of(path);
    if !dir.is_dir() {
        let why = if dir.exists() {
            "is a file, not a directory"
        } else {
            "does not exist"
        };
        return Err(IoError::invalid(
            path,
            format!("cannot write: directory '{}' {why}", dir.display()),
        ));
    }
    // (a link to a directory is replaced by the rename, as before: not followed here)
    if path.symlink_metadata().is_ok_and(|m| m.is_dir()) {
        return Err(IoError::invalid(
            path,
            "cannot write: this is a directory (give the name of a file inside it)",
        ));
    }
    let mut builder = tempfile::Builder::new();
    let prefix = format!(".{}.", name.to_string_lossy());
    builder.prefix(&prefix).suffix(".tmp");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    // created and registered under the registry's lock: a signal's cleanup, which holds the
    // lock until the program ends, never misses a temporary file that exists (created outside
    // it, a file made just before the cleanup and registered after it stayed behind: seen in CI)
    let (mut tmp, registered) = {
        let mut list = in_flight();
        let tmp = builder.tempfile_in(dir).map_err(|e| {
            IoError::io(
                path,
                "create a temporary file in the destination directory",
                e,
            )
        })?;
        let registered = Registered::push(&mut list, tmp.path());
        (tmp, registered)
    };
    let written = fill(&mut tmp, path, write);
    let value = match written {
        Ok(value) => value,
        Err(e) => {
            // the file first, then its registration: a signal's cleanup never misses it
            drop(tmp);
            drop(registered);
            return Err(e);
        }
    };
    // renamed and deregistered under the registry's lock: a signal's cleanup sees either a
    // temporary file to remove or a finished output, never a file between the two
    let mut list = in_flight();
    let persisted = tmp.persist(path).map(drop).map_err(|e| {
        // dropping the error's file removes it, still under the lock
        IoError::io(path, "move the finished temporary file into place", e.error)
    });
    registered.release(&mut list);
    persisted?;
    Ok(value)
}

/// The folder holding `file` (`.` for a bare file name): where an output's temporary file, or
/// a file's index (`predictions.json`, `aligned.json`), lies.
pub(crate) fn folder_of(file: &Path) -> &Path {
    match file.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// Runs a writer closure on the temporary file and flushes it.
fn fill<T>(
    tmp: &mut tempfile::NamedTempFile,
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> Result<T>,
) -> Result<T> {
    let mut w = BufWriter::new(tmp.as_file_mut());
    let value = write(&mut w)?;
    w.flush().map_err(|e| IoError::io(path, "write", e))?;
    Ok(value)
}

/// Maps an I/O error of a writer closure to [`IoError::Io`] with action "write".
pub(crate) fn write_err(path: &Path) -> impl Fn(std::io::Error) -> IoError + '_ {
    move |e| IoError::io(path, "write", e)
}

/// Whether `a` and `b` name the same file: equal once both resolve (links, `..`, relative
/// parts), or equal as written when either does not exist yet (an output about to be
/// created). What a command checks before it writes its output over one of its inputs.
pub fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}
