//! The one atomic writer (`occ_data::formats::io::write_atomic`), under concurrency: many threads,
//! and two processes, writing the same path at once always leave one writer's complete output, and
//! no temporary file behind.

use occ_data::formats::io::{temp_sibling, write_atomic};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A self-checking document of writer `id`, round `round`: a header with its length, a body that
/// depends on both, a trailer. Sizes vary from a few bytes to about 600 KB, so that interleaved or
/// torn writes show.
fn document(id: u64, round: u64) -> Vec<u8> {
    let len = ((id * 7919 + round * 104_729) % 600_000) as usize;
    let mut out = format!("LEN {len} ID {id} ROUND {round}\n").into_bytes();
    out.extend((0..len).map(|i| b'a' + ((i as u64 + id * 3 + round) % 26) as u8));
    out.extend_from_slice(b"\nEND\n");
    out
}

/// The document is one writer's complete output.
fn check(bytes: &[u8]) -> Result<(), String> {
    let text = std::str::from_utf8(bytes).map_err(|_| "not UTF-8".to_string())?;
    let header = text.lines().next().ok_or("empty")?;
    let f: Vec<&str> = header.split(' ').collect();
    if f.len() != 6 || f[0] != "LEN" || f[2] != "ID" || f[4] != "ROUND" {
        return Err(format!("bad header {header:?}"));
    }
    let (id, round): (u64, u64) = (
        f[3].parse().map_err(|_| "id")?,
        f[5].parse().map_err(|_| "round")?,
    );
    if document(id, round) != bytes {
        return Err(format!(
            "writer {id} round {round}: {} bytes, not the complete document",
            bytes.len()
        ));
    }
    Ok(())
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("occ-data-atomic-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn leftovers(dir: &Path, keep: &str) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n != keep)
        .collect()
}

/// `dir/out.json` holds one complete document and nothing else is left in `dir`.
fn assert_complete_and_alone(dir: &Path) {
    check(&std::fs::read(dir.join("out.json")).unwrap()).unwrap();
    let left = leftovers(dir, "out.json");
    assert!(left.is_empty(), "{left:?}");
}

#[test]
fn temporary_names_are_unique() {
    let p = Path::new("/some/dir/out.json");
    let names: HashSet<PathBuf> = (0..10_000).map(|_| temp_sibling(p)).collect();
    assert_eq!(names.len(), 10_000);
    for n in names.iter().take(3) {
        assert_eq!(n.parent(), p.parent());
        let f = n.file_name().unwrap().to_string_lossy().into_owned();
        assert!(f.starts_with(".out.json.tmp-"), "{f}");
        assert!(f.contains(&std::process::id().to_string()), "{f}");
    }
}

#[test]
fn concurrent_threads_leave_a_complete_file() {
    let dir = temp_dir("threads");
    let path = dir.join("out.json");
    let threads = 8u64;
    let rounds = 25u64;
    std::thread::scope(|s| {
        for id in 0..threads {
            let path = &path;
            s.spawn(move || {
                for round in 0..rounds {
                    write_atomic(path, &document(id, round)).unwrap();
                }
            });
        }
        // A reader meanwhile: every read sees a complete document (or none yet).
        let path = &path;
        s.spawn(move || {
            for _ in 0..200 {
                if let Ok(b) = std::fs::read(path) {
                    check(&b).unwrap();
                }
            }
        });
    });
    assert_complete_and_alone(&dir);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Run as a child process by [`two_processes_leave_a_complete_file`]: writes the document of
/// writer `ATOMIC_CHILD_ID` many times to `ATOMIC_CHILD_PATH`. A no-op in a normal test run.
#[test]
fn child_writer() {
    let (Some(path), Some(id)) = (
        std::env::var_os("ATOMIC_CHILD_PATH"),
        std::env::var("ATOMIC_CHILD_ID").ok(),
    ) else {
        return;
    };
    let id: u64 = id.parse().unwrap();
    for round in 0..40 {
        write_atomic(Path::new(&path), &document(id, round)).unwrap();
    }
}

#[test]
fn two_processes_leave_a_complete_file() {
    let dir = temp_dir("procs");
    let path = dir.join("out.json");
    let exe = std::env::current_exe().unwrap();
    for trial in 0..5u64 {
        let children: Vec<_> = (0..2u64)
            .map(|k| {
                Command::new(&exe)
                    .args(["--exact", "child_writer", "--test-threads", "1"])
                    .env("ATOMIC_CHILD_PATH", &path)
                    .env("ATOMIC_CHILD_ID", (100 + trial * 2 + k).to_string())
                    .stdout(std::process::Stdio::null())
                    .spawn()
                    .unwrap()
            })
            .collect();
        // Read while both write.
        let mut reads = 0;
        while reads < 100 {
            if let Ok(b) = std::fs::read(&path) {
                check(&b).unwrap();
            }
            reads += 1;
        }
        for mut c in children {
            assert!(c.wait().unwrap().success());
        }
        assert_complete_and_alone(&dir);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_failed_write_leaves_the_old_file_and_no_temporary() {
    let dir = temp_dir("fail");
    let path = dir.join("out.json");
    write_atomic(&path, &document(1, 1)).unwrap();
    // The target is now a folder: the rename fails, the old content stays, the temporary goes.
    let sub = dir.join("sub");
    std::fs::create_dir_all(sub.join("x")).unwrap();
    let e = write_atomic(&sub, b"data").unwrap_err().to_string();
    assert!(e.contains("sub"), "{e}");
    check(&std::fs::read(&path).unwrap()).unwrap();
    let mut left = leftovers(&dir, "out.json");
    left.retain(|n| n != "sub");
    assert!(left.is_empty(), "{left:?}");
    // A missing folder is an error naming the file.
    let e = write_atomic(&dir.join("no/such/out.json"), b"x")
        .unwrap_err()
        .to_string();
    assert!(e.contains("out.json"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
