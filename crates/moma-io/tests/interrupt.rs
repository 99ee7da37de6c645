//! What a program ended by a signal removes first: the temporary files of the outputs being
//! written. Its own test binary (one process): the cleanup removes every temporary file of the
//! process, which would break other tests' writes running beside it.

use moma_io::{IoError, atomic_write, remove_temporaries_in_flight};

fn io_err(path: &std::path::Path) -> impl Fn(std::io::Error) -> IoError + '_ {
    move |source| IoError::Io {
        path: path.to_path_buf(),
        action: "write",
        source,
    }
}

fn temporaries(dir: &std::path::Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".tmp"))
        .collect()
}

#[test]
fn the_cleanup_removes_the_temporaries_being_written_and_nothing_else() {
    let dir = tempfile::tempdir().unwrap();
    let done = dir.path().join("done.txt");
    atomic_write(&done, |w| w.write_all(b"old").map_err(io_err(&done))).unwrap();
    let path = dir.path().join("cloud.ply");
    let result = atomic_write(&path, |w| {
        w.write_all(b"half a point cloud").map_err(io_err(&path))?;
        w.flush().map_err(io_err(&path))?;
        // the writer is registered while it writes: its temporary file is there, then removed
        assert_eq!(temporaries(dir.path()).len(), 1);
        let (removed, held) = remove_temporaries_in_flight();
        assert_eq!((removed, held.len()), (1, 1));
        drop(held);
        assert!(temporaries(dir.path()).is_empty());
        Ok(())
    });
    // the rename of a removed temporary file fails: no half-written output appears
    assert!(result.is_err());
    assert!(!path.exists());
    assert_eq!(std::fs::read(&done).unwrap(), b"old");
    // finished writers left the registry
    let (removed, held) = remove_temporaries_in_flight();
    assert_eq!((removed, held.len()), (0, 0));
}
