//! `pathfarm guide`: train and save a tree, print statistics, pictures; bad
//! tree files are rejected cleanly.

use crate::common::*;

fn png_size(path: &std::path::Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(
        &bytes[..8],
        b"\x89PNG\r\n\x1a\n",
        "{} is not a PNG",
        path.display()
    );
    let be = |i: usize| u32::from_be_bytes(bytes[i..i + 4].try_into().unwrap());
    (be(16), be(20))
}

#[test]
fn guide_train_stats_show_and_scatter_produce_a_tree_and_pictures() {
    let dir = temp_dir("guide-cli");
    let scene = project_scene("door-ajar");
    let tree = dir.join("door.sdt");
    let res = ["-D", "resx=48", "-D", "resy=27"];
    let mut args = guide_train_args(&scene, &tree, "12");
    args.extend(res);
    let out = assert_success(&pathfarm(&args));
    let leaves: usize = out
        .lines()
        .find_map(|l| l.strip_prefix("spatial leaves: "))
        .and_then(|v| v.trim().parse().ok())
        .expect("leaves line");
    assert!(leaves > 1, "training refined the spatial tree: {out}");

    let stats = assert_success(&pathfarm(&["guide", "stats", path_str(&tree)]));
    assert!(
        stats.contains(&format!("spatial leaves: {leaves}")),
        "{stats}"
    );

    let quad = dir.join("quad.png");
    assert_success(&pathfarm(&guide_show_args(&tree, "0,1,0", &quad, "128")));
    assert_eq!(png_size(&quad), (128, 64));

    let scatter = dir.join("scatter.png");
    let mut args = guide_scatter_args(&scene, &tree, "20,20", &scatter, "64", "2000");
    args.extend(res);
    assert_success(&pathfarm(&args));
    assert_eq!(png_size(&scatter), (3 * 64 + 8, 32));
}

#[test]
fn corrupted_tree_file_is_rejected_naming_the_file() {
    let dir = temp_dir("guide-bad");
    let tree = dir.join("bad.sdt");
    std::fs::write(&tree, b"not a tree at all").unwrap();
    let o = pathfarm(&["guide", "stats", path_str(&tree)]);
    let err = assert_clean_failure(&o, "guide stats on a corrupted tree");
    assert!(err.contains("bad.sdt"), "{err}");
}
