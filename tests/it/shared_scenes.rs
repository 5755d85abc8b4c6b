//! The shared Bitterli scenes load and render.

use crate::common::*;

#[test]
fn veach_ajar_loads_and_renders_finite_light() {
    let film = render_file(
        &shared_scene("veach-ajar"),
        &[("resx", "32"), ("resy", "18")],
        4,
        1,
    );
    let m = film.mean_rgb();
    assert!(m
        .iter()
        .all(|p| p.iter().all(|c| c.is_finite() && *c >= 0.0)));
    let mean: f32 = m.iter().map(|p| p[0] + p[1] + p[2]).sum::<f32>() / (3 * m.len()) as f32;
    assert!(mean > 0.01, "the room is lit through the door: mean {mean}");
}
