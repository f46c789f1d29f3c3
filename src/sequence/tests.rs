use super::*;

#[test]
fn the_three_pattern_conventions_name_the_same_files() {
    for p in ["v/cloud.####.vdb", "v/cloud.%04d.vdb", "v/cloud.$F4.vdb"] {
        let pattern = FramePattern::parse(p).unwrap();
        assert_eq!(pattern.path(1001), PathBuf::from("v/cloud.1001.vdb"), "{p}");
        assert_eq!(pattern.path(7), PathBuf::from("v/cloud.0007.vdb"), "{p}");
        assert_eq!(
            pattern.path(12345),
            PathBuf::from("v/cloud.12345.vdb"),
            "{p}"
        );
        assert_eq!(pattern.frame_of("v/cloud.1001.vdb"), Some(1001), "{p}");
        assert_eq!(pattern.frame_of("v/cloud.12345.vdb"), Some(12345), "{p}");
        // Padded wider than the pattern, or too short: another sequence's file.
        assert_eq!(pattern.frame_of("v/cloud.01001.vdb"), None, "{p}");
        assert_eq!(pattern.frame_of("v/cloud.101.vdb"), None, "{p}");
        assert_eq!(pattern.frame_of("v/cloud.10a1.vdb"), None, "{p}");
    }
    let unpadded = FramePattern::parse("c.$F.vdb").unwrap();
    assert_eq!(unpadded.path(42), PathBuf::from("c.42.vdb"));
    assert_eq!(FramePattern::parse("c.%d.vdb").unwrap(), unpadded);
    assert_eq!(FramePattern::parse("plain.vdb"), None);
}

#[test]
fn frame_ranges_parse_and_refuse() {
    assert_eq!(
        FrameRange::parse("1001-1240:2").unwrap(),
        FrameRange {
            first: 1001,
            last: 1240,
            step: 2
        }
    );
    let one = FrameRange::parse("7").unwrap();
    assert_eq!(one.frames().collect::<Vec<_>>(), vec![7]);
    let neg = FrameRange::parse("-2-2").unwrap();
    assert_eq!(neg.frames().count(), 5);
    for bad in ["", "a-b", "10-1", "1-10:0", "1-10:-1", "1-99999999"] {
        assert!(FrameRange::parse(bad).is_err(), "{bad:?}");
    }
    let r = FrameRange::parse("1-9:4").unwrap();
    assert_eq!(r.frames().collect::<Vec<_>>(), vec![1, 5, 9]);
    assert!(r.contains(5) && !r.contains(6) && !r.contains(13));
}

#[test]
fn shards_split_every_frame_exactly_once() {
    let items: Vec<usize> = (0..25).collect();
    let mut all: Vec<usize> = (1..=3)
        .flat_map(|k| Shard { index: k, count: 3 }.select(items.clone()))
        .collect();
    all.sort();
    assert_eq!(all, items);
    for bad in ["0/3", "4/3", "1/0", "x/3", "3"] {
        assert!(Shard::parse(bad).is_err(), "{bad}");
    }
    assert_eq!(Shard::parse("2/3").unwrap(), Shard { index: 2, count: 3 });
}

#[test]
fn resolve_finds_frames_and_names_the_missing() {
    let dir = tempfile::tempdir().unwrap();
    for n in [1, 2, 3, 5, 10] {
        std::fs::write(dir.path().join(format!("c.{n:04}.vdb")), b"x").unwrap();
    }
    std::fs::write(dir.path().join("c.00001.vdb"), b"other sequence").unwrap();
    let d = dir.path().display();
    let all = resolve(&[format!("{d}/c.####.vdb")], None).unwrap();
    let numbers: Vec<i64> = all.frames.iter().filter_map(|f| f.number).collect();
    assert_eq!(numbers, vec![1, 2, 3, 5, 10]);
    let glob = resolve(&[format!("{d}/c.[0-9][0-9][0-9][0-9].vdb")], None).unwrap();
    assert_eq!(glob.frames, all.frames);

    let ranged = resolve(&[format!("{d}/c.%04d.vdb")], FrameRange::parse("1-5").ok()).unwrap();
    assert_eq!(ranged.frames.len(), 4);
    assert_eq!(ranged.missing, vec![dir.path().join("c.0004.vdb")]);

    assert!(resolve(&[format!("{d}/z.####.vdb")], None).is_err());
    assert!(resolve(&[format!("{d}/z*.vdb")], None).is_err());
}

#[test]
fn outputs_mirror_inputs_and_collisions_are_refused() {
    let frames = |names: &[&str]| -> Vec<Frame> {
        names
            .iter()
            .map(|n| Frame {
                number: None,
                path: PathBuf::from(n),
            })
            .collect()
    };
    let out = outputs_in(
        Path::new("o"),
        &frames(&["a/c.1001.vdb", "a/c.1002.vdb"]),
        "vtc",
    )
    .unwrap();
    assert_eq!(out[0], PathBuf::from("o/c.1001.vtc"));
    let err = outputs_in(Path::new("o"), &frames(&["a/c.1.vdb", "b/c.1.vdb"]), "vtc").unwrap_err();
    assert!(err.to_string().contains("would both write"), "{err}");
}

#[test]
fn images_are_named_by_frame_and_map() {
    let frames = vec![
        (
            0,
            Frame {
                number: Some(1001),
                path: PathBuf::from("c.1001.vtc"),
            },
        ),
        (
            1,
            Frame {
                number: None,
                path: PathBuf::from("c.vtc"),
            },
        ),
    ];
    let one = image_names(Path::new("o/img.####.exr"), &frames, &["sky".into()]).unwrap();
    assert_eq!(one[0], vec![PathBuf::from("o/img.1001.exr")]);
    assert_eq!(one[1], vec![PathBuf::from("o/img.0002.exr")]);
    let maps = ["sky".to_string(), "env/studio.exr".to_string()];
    let two = image_names(Path::new("o/img.%04d.png"), &frames, &maps).unwrap();
    assert_eq!(
        two[0],
        vec![
            PathBuf::from("o/img.sky.1001.png"),
            PathBuf::from("o/img.studio.1001.png")
        ]
    );
    let single = image_names(Path::new("a.exr"), &frames[..1], &maps).unwrap();
    assert_eq!(single[0][1], PathBuf::from("a.studio.exr"));
    let same = ["a/studio.exr".to_string(), "b/studio.hdr".to_string()];
    assert!(image_names(Path::new("x.####.exr"), &frames, &same).is_err());
}
