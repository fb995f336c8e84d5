//! Atomic outputs. Staged directories: nothing appears at the destination until `finish`, a dropped stage
//! leaves nothing behind, and finishing into an existing directory replaces namesakes and keeps the rest.
//! Files written through a path: whole or not at all.
use mvmp_io::StagedDir;

fn names(dir: &std::path::Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    v.sort();
    v
}

#[test]
fn a_staged_directory_appears_whole_or_not_at_all() {
    let root = tempfile::tempdir().unwrap();
    let dest = root.path().join("out");

    // Dropped before finishing: the destination never appears and the stage is gone.
    {
        let s = StagedDir::new(&dest).unwrap();
        std::fs::create_dir_all(s.path().join("a")).unwrap();
        std::fs::write(s.path().join("a/x.txt"), "1").unwrap();
        assert!(!dest.exists());
    }
    assert!(names(root.path()).is_empty(), "{:?}", names(root.path()));

    // Finished into a missing destination: moved whole.
    let s = StagedDir::new(&dest).unwrap();
    std::fs::create_dir_all(s.path().join("a")).unwrap();
    std::fs::write(s.path().join("a/x.txt"), "1").unwrap();
    std::fs::write(s.path().join("keep.txt"), "k").unwrap();
    s.finish().unwrap();
    assert_eq!(names(&dest), ["a", "keep.txt"]);
    assert_eq!(names(root.path()), ["out"]);

    // Finished into an existing destination: namesakes replaced, other files kept, subtrees merged.
    let s = StagedDir::new(&dest).unwrap();
    std::fs::create_dir_all(s.path().join("a")).unwrap();
    std::fs::write(s.path().join("a/x.txt"), "2").unwrap();
    std::fs::write(s.path().join("a/y.txt"), "3").unwrap();
    s.finish().unwrap();
    assert_eq!(names(&dest), ["a", "keep.txt"]);
    assert_eq!(names(&dest.join("a")), ["x.txt", "y.txt"]);
    assert_eq!(std::fs::read_to_string(dest.join("a/x.txt")).unwrap(), "2");
    assert_eq!(std::fs::read_to_string(dest.join("keep.txt")).unwrap(), "k");
    assert_eq!(names(root.path()), ["out"]);
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&dest).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o755, "the destination keeps its usual permissions");
    }

    // A file of the destination that the stage holds a directory of is replaced by that directory.
    let s = StagedDir::new(&dest).unwrap();
    std::fs::create_dir_all(s.path().join("keep.txt")).unwrap();
    std::fs::write(s.path().join("keep.txt/inner"), "i").unwrap();
    s.finish().unwrap();
    assert_eq!(names(&dest.join("keep.txt")), ["inner"]);
    assert_eq!(names(&dest.join("a")), ["x.txt", "y.txt"]);
    assert_eq!(names(root.path()), ["out"]);

    // With the command's own outputs named, an earlier run's that this one does not write go, at
    // any depth; other files stay.
    std::fs::write(dest.join("mesh_2.obj"), "old").unwrap();
    std::fs::write(dest.join("a/mesh_9.obj"), "old").unwrap();
    let s = StagedDir::new(&dest)
        .unwrap()
        .owning(|n| n.starts_with("mesh_"));
    std::fs::create_dir_all(s.path().join("a")).unwrap();
    std::fs::write(s.path().join("mesh_0.obj"), "new").unwrap();
    std::fs::write(s.path().join("a/mesh_0.obj"), "new").unwrap();
    s.finish().unwrap();
    assert_eq!(names(&dest), ["a", "keep.txt", "mesh_0.obj"]);
    assert_eq!(names(&dest.join("a")), ["mesh_0.obj", "x.txt", "y.txt"]);

    // A destination that is a file is an error naming it.
    let file = root.path().join("file");
    std::fs::write(&file, "f").unwrap();
    let s = StagedDir::new(&file).unwrap();
    std::fs::write(s.path().join("z.txt"), "z").unwrap();
    let e = s.finish().unwrap_err().to_string();
    assert!(e.contains("file") && e.contains("not a directory"), "{e}");
    assert_eq!(names(root.path()), ["file", "out"]);
}

#[test]
fn a_file_written_through_a_path_appears_whole_or_not_at_all() {
    use mvmp_io::IoError;
    use mvmp_io::write_atomic_via;
    let dir = tempfile::tempdir().unwrap();
    let dest = dir.path().join("optim.bpk");
    // A writer that, like burn's burnpack writer, adds an extension to a path that has none: the
    // temporary path must already carry the destination's.
    let write = |p: &std::path::Path, text: &str| -> Result<(), IoError> {
        let p = if p.extension().is_none() {
            p.with_extension("bpk")
        } else {
            p.to_path_buf()
        };
        std::fs::write(&p, text).map_err(|source| IoError::Io { path: p, source })
    };
    write_atomic_via(&dest, |p| write(p, "first")).unwrap();
    assert_eq!(std::fs::read_to_string(&dest).unwrap(), "first");
    // A failing writer leaves the destination as it was and no temporary file behind.
    let failed = write_atomic_via(&dest, |p| {
        write(p, "half")?;
        Err(IoError::Io {
            path: p.to_path_buf(),
            source: std::io::Error::other("disk full"),
        })
    });
    assert!(failed.is_err());
    assert_eq!(std::fs::read_to_string(&dest).unwrap(), "first");
    assert_eq!(names(dir.path()), vec!["optim.bpk".to_string()]);
}

#[test]
fn a_json_error_names_the_key_path() {
    #[derive(serde::Deserialize, Debug)]
    #[allow(dead_code)]
    struct Person {
        pelvis: [f64; 3],
    }
    #[derive(serde::Deserialize, Debug)]
    #[allow(dead_code)]
    struct Frame {
        people: Vec<Person>,
    }
    let e = mvmp_io::parse_json::<Frame>(
        r#"{"people": [{"pelvis": [0, 1, 2]}, {"pelvis": [0, null, 2]}]}"#,
    )
    .unwrap_err();
    assert!(
        e.starts_with("key `people[1].pelvis[1]`: invalid type: null"),
        "{e}"
    );
    let e = mvmp_io::parse_json::<Frame>("{").unwrap_err();
    assert!(e.contains("line 1"), "{e}");
    // A fixed-length array given too many values says so, not only "trailing characters".
    let e = mvmp_io::parse_json::<Frame>(r#"{"people": [{"pelvis": [0, 1, 2, 3]}]}"#).unwrap_err();
    assert!(
        e.starts_with("key `people[0].pelvis`: more elements than it takes"),
        "{e}"
    );
}

#[test]
#[cfg(target_os = "linux")]
fn a_new_output_sweeps_what_killed_processes_left_beside_it() {
    use mvmp_io::{partial_prefix_of, write_atomic};
    let root = tempfile::tempdir().unwrap();
    // A process that has exited: its id names no live process (ids are not reused this quickly).
    let mut child = std::process::Command::new("true").spawn().unwrap();
    let dead = child.id();
    child.wait().unwrap();
    let live = std::process::id();
    let stale_dir = format!("{}AbC123", partial_prefix_of(dead));
    let stale_file = format!("{}XyZ789.bpk", partial_prefix_of(dead));
    let running = format!("{}Qq1", partial_prefix_of(live));
    // Another machine's, in a directory both share: its process may be running there.
    let elsewhere = format!(".mvmp-partial-{dead}@othermachine0-Zz9");
    for d in [&stale_dir, &running] {
        std::fs::create_dir(root.path().join(d)).unwrap();
        std::fs::write(root.path().join(d).join("x"), "x").unwrap();
    }
    // Names this module does not make (no process id, another prefix) are not its to remove.
    for f in [
        &stale_file,
        &elsewhere,
        ".mvmp-partial-old",
        ".tmpAbc",
        "notes.txt",
    ] {
        std::fs::write(root.path().join(f), "f").unwrap();
    }
    write_atomic(&root.path().join("out.json"), b"{}").unwrap();
    let mut expect = vec![
        elsewhere.clone(),
        ".mvmp-partial-old".to_string(),
        running.clone(),
        ".tmpAbc".into(),
        "notes.txt".into(),
        "out.json".into(),
    ];
    expect.sort();
    assert_eq!(names(root.path()), expect);

    // A staged directory sweeps its parent the same way.
    std::fs::create_dir(root.path().join(&stale_dir)).unwrap();
    let s = StagedDir::new(&root.path().join("dest")).unwrap();
    std::fs::write(s.path().join("a"), "a").unwrap();
    s.finish().unwrap();
    expect.push("dest".into());
    expect.sort();
    assert_eq!(names(root.path()), expect);
}

#[test]
fn a_destination_named_through_dot_dot_is_staged_beside_it_not_inside() {
    let root = tempfile::tempdir().unwrap();
    let dest = root.path().join("out");
    std::fs::create_dir_all(dest.join("sub")).unwrap();
    std::fs::write(dest.join("old.txt"), "o").unwrap();
    // `out/sub/..` is `out`: a stage in its lexical parent (`out/sub`) would lie inside it.
    let s = StagedDir::new(&dest.join("sub/..")).unwrap();
    assert!(!s.path().starts_with(&dest), "{}", s.path().display());
    std::fs::write(s.path().join("new.txt"), "n").unwrap();
    s.finish().unwrap();
    assert_eq!(names(&dest), ["new.txt", "old.txt", "sub"]);
    assert_eq!(names(root.path()), ["out"]);
}

/// A long message is cut at a character boundary and says how much was left out; a short one is kept.
#[test]
fn brief_messages_keep_their_start_and_count_the_rest() {
    use mvmp_io::brief;
    assert_eq!(brief("short", 10), "short");
    assert_eq!(brief("exactly10!", 10), "exactly10!");
    let long = format!("header: {}", "é".repeat(70_000));
    let b = brief(&long, 20);
    assert_eq!(
        b,
        format!("header: {}... (69988 more characters)", "é".repeat(12))
    );
}
