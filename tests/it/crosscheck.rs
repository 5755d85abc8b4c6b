//! Cross-check against an independent renderer: Mitsuba 3 (from PyPI) renders
//! the same XML; image means must agree within 1 % and a per-pixel Z-test
//! must pass for at least 99 % of pixels (tests/crosscheck/crosscheck.py).
//!
//! These need `python3` with `mitsuba` and `numpy` (./test.sh installs them);
//! without them the tests fail and say so.

use std::process::Command;

use crate::common::*;

fn crosscheck(scene: &std::path::Path, extra: &[&str]) {
    let script = repo_root().join("tests/crosscheck/crosscheck.py");
    let out_dir = temp_dir("crosscheck");
    let o = Command::new("python3")
        .arg(&script)
        .arg("--pathfarm")
        .arg(env!("CARGO_BIN_EXE_pathfarm"))
        .arg("--scene")
        .arg(scene)
        .arg("--out")
        .arg(&out_dir)
        .args(extra)
        .output()
        .expect("python3 must be installed to run the Mitsuba cross-check");
    let stdout = String::from_utf8_lossy(&o.stdout);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.success(),
        "cross-check failed for {}:\n{stdout}\n{stderr}",
        scene.display()
    );
}

#[test]
fn cornell_box_agrees_with_mitsuba() {
    crosscheck(&shared_scene("cornell-box"), &[]);
}

#[test]
fn materials_scene_agrees_with_mitsuba() {
    crosscheck(&project_scene("materials"), &[]);
}

/// An emitting shape without a BSDF is black, and a rotation axis is used as given (not
/// normalised), as in Mitsuba 3.
#[test]
fn lamp_room_agrees_with_mitsuba() {
    crosscheck(&project_scene("lamp-room"), &[]);
}

/// An environment map's rows sit on the poles and its columns' centres at (x + 0.5) / width.
#[test]
fn envmap_sky_agrees_with_mitsuba() {
    crosscheck(&project_scene("envmap-sky"), &[]);
}

/// A `spot` emitter's cone and linear falloff, rendered with Mitsuba's `direct` integrator.
#[test]
fn spotlight_agrees_with_mitsuba() {
    crosscheck(&project_scene("spotlight"), &[]);
}

/// Analytic cylinders: a pipe seen inside and out, a scaled column, a tube light sampled by
/// area.
#[test]
fn cylinders_agree_with_mitsuba() {
    crosscheck(&project_scene("cylinders"), &[]);
}

/// Instancing: a shapegroup placed four times (rotated, scaled, mirrored).
#[test]
fn instances_agree_with_mitsuba() {
    crosscheck(&project_scene("instances"), &[]);
}

/// A Mitsuba 0.6 scene: camelCase names, `<path>`, `<include>`, a serialized mesh file of two
/// shapes, spectra as wavelength:value pairs, a uniform spectrum on an emitter.
#[test]
fn legacy_scene_agrees_with_mitsuba() {
    crosscheck(&project_scene("legacy-0.6"), &[]);
}

/// Surfaces light passes through: `mask` with an opacity texture (a patterned shadow) and a
/// constant, `null` with and without an emitter. Mitsuba's shadow rays stop at a mask, so
/// its estimate of the light behind one is heavy-tailed: 64 runs steady its variance.
#[test]
fn cutouts_agree_with_mitsuba() {
    crosscheck(&project_scene("cutouts"), &["--runs", "64"]);
}

/// Perturbed shading normals: `bumpmap` on a mesh and a sphere, `normalmap` under a rough
/// conductor and a two-sided diffuse panel (the shading frame follows dp/du, the shadowing
/// term and the side rule apply).
#[test]
fn bumps_agree_with_mitsuba() {
    crosscheck(&project_scene("bumps"), &[]);
}

/// `guided_path` (through `--integrator`) against Mitsuba's path tracer: guiding is
/// unbiased, so the images agree where guiding meets a black emitter BSDF and scaling
/// rotations (lamp-room), an environment map's mapping (envmap-sky), a spot light's cone
/// (spotlight), analytic cylinders (cylinders), instancing (instances), surfaces paths pass
/// through (cutouts), perturbed normals (bumps) and a Mitsuba 0.6 file's features
/// (legacy-0.6: serialized meshes, includes, spectra).
#[test]
fn guided_path_agrees_with_mitsuba_on_the_scenes_of_mitsuba_features() {
    let guided = ["--pf-integrator", "guided_path", "-D", "integrator=path"];
    for scene in [
        "lamp-room",
        "envmap-sky",
        "spotlight",
        "cylinders",
        "instances",
        "bumps",
        "legacy-0.6",
    ] {
        crosscheck(&project_scene(scene), &guided);
    }
    let runs = ["--runs", "64"];
    crosscheck(
        &project_scene("cutouts"),
        &[&guided[..], &runs[..]].concat(),
    );
}
