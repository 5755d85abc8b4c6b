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
    let scene = scene.to_str().unwrap();
    let tree = dir.join("door.sdt");
    let res = ["-D", "resx=48", "-D", "resy=27"];
    let mut args = vec![
        "guide",
        "train",
        scene,
        "-o",
        tree.to_str().unwrap(),
        "--spp",
        "12",
    ];
    args.extend(res);
    let o = pathfarm(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = String::from_utf8_lossy(&o.stdout);
    let leaves: usize = out
        .lines()
        .find_map(|l| l.strip_prefix("spatial leaves: "))
        .and_then(|v| v.trim().parse().ok())
        .expect("leaves line");
    assert!(leaves > 1, "training refined the spatial tree: {out}");

    let o = pathfarm(&["guide", "stats", tree.to_str().unwrap()]);
    assert!(
        o.status.success()
            && String::from_utf8_lossy(&o.stdout).contains(&format!("spatial leaves: {leaves}"))
    );

    let quad = dir.join("quad.png");
    let o = pathfarm(&[
        "guide",
        "show",
        tree.to_str().unwrap(),
        "--point",
        "0,1,0",
        "-o",
        quad.to_str().unwrap(),
        "--width",
        "128",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(png_size(&quad), (128, 64));

    let scatter = dir.join("scatter.png");
    let mut args = vec![
        "guide",
        "scatter",
        scene,
        "--tree",
        tree.to_str().unwrap(),
        "--pixel",
        "20,20",
        "-o",
        scatter.to_str().unwrap(),
        "--width",
        "64",
        "--samples",
        "2000",
    ];
    args.extend(res);
    let o = pathfarm(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(png_size(&scatter), (3 * 64 + 8, 32));
}

#[test]
fn corrupted_tree_file_is_rejected_naming_the_file() {
    let dir = temp_dir("guide-bad");
    let tree = dir.join("bad.sdt");
    std::fs::write(&tree, b"not a tree at all").unwrap();
    let o = pathfarm(&["guide", "stats", tree.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("bad.sdt") && !err.contains("panicked"),
        "{err}"
    );
}
