//! Names are not paths (issue 69, item 2): a camera name from `--cameras`,
//! a video feature key given to the LeRobot writer or used as the `calc`
//! mask cache's folder each become one path component, so each must be a
//! plain name. `..`, `/`, an empty name or a NUL is refused with the flag or
//! field and the value named, before any file is created or read.
#![allow(clippy::unwrap_used)]

use bridgev2w_data::clip_masks::calc_cache_path;
use bridgev2w_data::lerobot::LeRobotV3Writer;
use bridgev2w_data::raw::agibot::{self, AgibotOptions, EpisodeKey};
use bridgev2w_data::raw::RawError;

/// Names that would leave (or collapse) the folder they are joined to.
const NOT_NAMES: [&str; 6] = ["..", ".", "", "../outside", "a/../../b", "a\0b"];

#[test]
fn the_mask_cache_folder_of_a_video_key_is_a_plain_name() {
    let tmp = tempfile::tempdir().unwrap();
    let cache = tmp.path().join("cache");
    let ok = calc_cache_path(&cache, "observation.images.main", 3, (96, 64)).unwrap();
    assert_eq!(
        ok,
        cache.join("observation.images.main/episode_000003_96x64.npy")
    );
    // A '/' in a key stays inside the cache (as '_').
    let slash = calc_cache_path(&cache, "a/b", 0, (8, 8)).unwrap();
    assert!(slash.starts_with(cache.join("a_b")), "{}", slash.display());
    for key in ["..", ".", ""] {
        let e = calc_cache_path(&cache, key, 0, (8, 8))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("video_key") && e.contains(&format!("{key:?}")) && e.contains("plain name"),
            "{key:?}: {e}"
        );
    }
}

#[test]
fn the_lerobot_writer_refuses_a_video_key_that_is_not_a_name() {
    let tmp = tempfile::tempdir().unwrap();
    for key in NOT_NAMES {
        let root = tmp.path().join("out");
        let e = LeRobotV3Writer::new(&root, "r", 8, key, (16, 16), vec![], vec![])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("video key") && e.contains("expected a plain name"),
            "{key:?}: {e}"
        );
        // Refused before anything was created.
        assert!(!root.exists(), "{key:?} created {}", root.display());
        assert!(!tmp.path().join("outside").exists(), "{key:?}");
    }
    // A plain key is accepted.
    let root = tmp.path().join("ok");
    let _w = LeRobotV3Writer::new(
        &root,
        "r",
        8,
        "observation.images.main",
        (16, 16),
        vec![],
        vec![],
    )
    .unwrap();
    assert!(root.is_dir());
}

#[test]
fn agibot_camera_names_are_plain_names() {
    let ok = AgibotOptions {
        cameras: vec!["head".into(), "hand_left".into()],
        ..AgibotOptions::default()
    };
    ok.check_cameras().unwrap();
    for cam in NOT_NAMES {
        let opts = AgibotOptions {
            cameras: vec!["head".into(), cam.into()],
            ..AgibotOptions::default()
        };
        let e = opts.check_cameras().unwrap_err();
        assert!(
            e.contains("--cameras") && e.contains("expected a plain name"),
            "{cam:?}: {e}"
        );
    }
}

#[test]
fn agibot_reading_refuses_a_camera_path_before_opening_anything() {
    // A recording whose episode exists, and a file beside it that a camera
    // name of "../" components would reach.
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("agibot");
    std::fs::create_dir_all(root.join("proprio_stats/t/e")).unwrap();
    std::fs::write(root.join("proprio_stats/t/e/proprio_stats.h5"), b"not hdf5").unwrap();
    std::fs::write(tmp.path().join("secret_color.mp4"), b"SECRET-CONTENT").unwrap();
    let key = EpisodeKey {
        task: "t".into(),
        episode: "e".into(),
    };
    let opts = AgibotOptions {
        cameras: vec!["../../../../secret".into()],
        ..AgibotOptions::default()
    };
    let e = agibot::read_episode(&root, &key, &opts).unwrap_err();
    assert!(matches!(e, RawError::Inconsistent { .. }), "{e}");
    let e = e.to_string();
    assert!(
        e.contains("--cameras")
            && e.contains("../../../../secret")
            && !e.contains("SECRET-CONTENT"),
        "{e}"
    );
}
