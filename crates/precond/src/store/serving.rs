//! One server per SQLite file: an exclusive lock held for the serving process's lifetime.
//!
//! A SQLite file is served by one process: two servers on one file would each claim the fits,
//! and SQLite answers one of them `database is locked` under concurrent writes. `precond
//! serve` therefore takes an advisory `flock` on `<database>.lock` before it opens the file; a
//! second server on the same file (by any path: the lock is on the file's absolute path, links
//! resolved) refuses to start, naming the process that holds it. The kernel releases the lock
//! when the process ends, however it ends (`kill -9` included), so a restart never finds a
//! stale lock. The lock is on a file of its own, never on the database: closing a descriptor
//! of the database itself would drop SQLite's own POSIX locks.

use anyhow::Context;
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

/// Held while a process serves a SQLite file; released when dropped (or when the process
/// ends).
#[derive(Debug)]
pub struct ServingLock {
    /// The lock file, open and locked.
    _file: std::fs::File,
    /// Its path.
    path: PathBuf,
}

impl ServingLock {
    /// The lock file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Takes the serving lock of the SQLite database at `url` (a path or a `sqlite:` URL), or
/// fails with a message naming the process that holds it. `Ok(None)` for PostgreSQL, which
/// replicas share.
pub fn lock_for_serving(url: &str) -> anyhow::Result<Option<ServingLock>> {
    if super::Backend::of_url(url) != super::Backend::Sqlite {
        return Ok(None);
    }
    let options = super::sqlite_options(url)?;
    let db = options.get_filename();
    // Resolve links when the file exists, so two paths to one file share one lock.
    let db = std::fs::canonicalize(db).unwrap_or_else(|_| db.to_path_buf());
    let mut name = db.as_os_str().to_owned();
    name.push(".lock");
    let path = PathBuf::from(name);
    let mut file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .with_context(|| format!("opening the lock file {}", path.display()))?;
    if !try_lock(&file)? {
        let mut holder = String::new();
        let _ = file.read_to_string(&mut holder);
        let holder = holder.trim();
        anyhow::bail!(
            "the database {} is already served by another precond process ({}); a SQLite \
             file is served by one process: stop that server first, or serve several replicas \
             over PostgreSQL (lock file {})",
            db.display(),
            if holder.is_empty() {
                "which has not written its id yet".to_string()
            } else {
                holder.to_string()
            },
            path.display()
        );
    }
    // Who holds it, for the message above (advisory: the lock itself is what counts).
    file.set_len(0)?;
    file.rewind()?;
    write!(
        file,
        "pid {}, since {}",
        std::process::id(),
        super::timestamp(time::OffsetDateTime::now_utc())
    )?;
    file.flush()?;
    Ok(Some(ServingLock { _file: file, path }))
}

/// `flock(LOCK_EX | LOCK_NB)`: `false` when another open file holds it.
#[cfg(unix)]
fn try_lock(file: &std::fs::File) -> anyhow::Result<bool> {
    use std::os::fd::AsRawFd;
    // SAFETY: the descriptor is open for the duration of the call.
    let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
    if rc == 0 {
        return Ok(true);
    }
    let e = std::io::Error::last_os_error();
    if e.raw_os_error() == Some(libc::EWOULDBLOCK) {
        Ok(false)
    } else {
        Err(anyhow::Error::new(e).context("locking the database's lock file"))
    }
}

/// Elsewhere: no advisory lock is taken (the documentation's rule still holds).
#[cfg(not(unix))]
fn try_lock(_file: &std::fs::File) -> anyhow::Result<bool> {
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_on_one_file_is_refused_naming_the_holder_and_freed_on_drop() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("one.db");
        std::fs::write(&db, b"").unwrap();
        let first = lock_for_serving(db.to_str().unwrap()).unwrap().unwrap();
        assert!(first.path().ends_with("one.db.lock"));
        // Another path to the same file: a link.
        let link = dir.path().join("link.db");
        std::os::unix::fs::symlink(&db, &link).unwrap();
        for other in [
            db.to_str().unwrap().to_string(),
            format!("sqlite://{}", link.display()),
        ] {
            let e = lock_for_serving(&other).unwrap_err().to_string();
            assert!(e.contains("already served"), "{e}");
            assert!(e.contains(&format!("pid {}", std::process::id())), "{e}");
        }
        drop(first);
        assert!(lock_for_serving(link.to_str().unwrap()).unwrap().is_some());
        assert!(lock_for_serving("postgres://u@h/db").unwrap().is_none());
    }
}
