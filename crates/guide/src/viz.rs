//! Visualisation: rasterise a quadtree's sampling pdf into an RGB image.

use crate::dtree::SamplingDTree;
use glam::Vec2;

/// False-colour map of `t` in `[0, 1]`: black -> blue -> red -> yellow -> white.
pub fn heat(t: f32) -> [f32; 3] {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let stops: [[f32; 3]; 5] = [
        [0.0, 0.0, 0.0],
        [0.1, 0.1, 0.8],
        [0.9, 0.1, 0.1],
        [1.0, 0.9, 0.1],
        [1.0, 1.0, 1.0],
    ];
    let x = t * 4.0;
    let i = (x.floor() as usize).min(3);
    let f = x - i as f32;
    let (a, b) = (stops[i], stops[i + 1]);
    [
        a[0] + (b[0] - a[0]) * f,
        a[1] + (b[1] - a[1]) * f,
        a[2] + (b[2] - a[2]) * f,
    ]
}

/// A heat map of how many of `dirs` fall in each pixel of a `width x width / 2` picture of
/// the sphere of directions laid out as [`rasterize_pdf`] lays out a quadtree (column: `u`,
/// row: `v` of [`crate::mapping::dir_to_uv`]), scaled to the fullest pixel: RGB, row major,
/// 3 floats a pixel.
pub fn histogram(dirs: &[glam::Vec3], width: usize) -> Vec<f32> {
    let height = width / 2;
    let mut counts = vec![0u32; width * height];
    for d in dirs {
        let uv = crate::mapping::dir_to_uv(*d);
        let x = ((uv.x * width as f32) as usize).min(width - 1);
        let y = ((uv.y * height as f32) as usize).min(height - 1);
        counts[y * width + x] += 1;
    }
    let max = counts.iter().copied().max().unwrap_or(0).max(1) as f32;
    counts.iter().flat_map(|&c| heat(c as f32 / max)).collect()
}

/// Rasterises the pdf over `(u, v)` of `tree` into a `width * height` RGB image, row major,
/// 3 floats per pixel: column x covers `u` in `[x/width, (x+1)/width)`, row y covers `v` in
/// `[y/height, (y+1)/height)` (pixel centres sampled). Values are `pdf / max pdf` through
/// [`heat`]; `outlines` draws the leaf-cell borders in green.
pub fn rasterize_pdf(
    tree: &SamplingDTree,
    width: usize,
    height: usize,
    outlines: bool,
) -> Vec<f32> {
    let mut pdf = vec![0.0f32; width * height];
    let mut max = 0.0f32;
    for y in 0..height {
        for x in 0..width {
            let uv = Vec2::new(
                (x as f32 + 0.5) / width as f32,
                (y as f32 + 0.5) / height as f32,
            );
            let p = tree.pdf(uv);
            pdf[y * width + x] = p;
            max = max.max(p);
        }
    }
    let mut img = Vec::with_capacity(width * height * 3);
    for &p in &pdf {
        let c = heat(if max > 0.0 { p / max } else { 0.0 });
        img.extend_from_slice(&c);
    }
    if outlines {
        let green = [0.0f32, 1.0, 0.0];
        let mut put = |x: usize, y: usize| {
            if x < width && y < height {
                img[(y * width + x) * 3..(y * width + x) * 3 + 3].copy_from_slice(&green);
            }
        };
        for c in tree.tree().leaf_cells() {
            let x0 = (c.origin[0] * width as f64).floor() as usize;
            let y0 = (c.origin[1] * height as f64).floor() as usize;
            let x1 = ((c.origin[0] + c.size) * width as f64).ceil() as usize;
            let y1 = ((c.origin[1] + c.size) * height as f64).ceil() as usize;
            if x1 - x0 < 2 || y1 - y0 < 2 {
                continue; // too small to outline at this resolution
            }
            for x in x0..x1 {
                put(x, y0);
            }
            for y in y0..y1 {
                put(x0, y);
            }
        }
    }
    img
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dtree::DTree;
    use crate::stats::to_fixed;
    use std::sync::atomic::AtomicU64;

    #[test]
    fn viz_rasterises_the_pdf_with_its_peak_brightest() {
        let ov = AtomicU64::new(0);
        let mut t = DTree::uniform(3); // 8 x 8 cells
        t.deposit(Vec2::new(0.3, 0.8), to_fixed(10.0).0, &ov); // cell (2, 6)
        t.deposit(Vec2::new(0.9, 0.1), to_fixed(1.0).0, &ov); // cell (7, 0)
        t.build();
        let t = t.freeze();
        let img = crate::viz::rasterize_pdf(&t, 64, 32, false);
        assert_eq!(img.len(), 64 * 32 * 3);
        let px = |x: usize, y: usize| {
            [
                img[(y * 64 + x) * 3],
                img[(y * 64 + x) * 3 + 1],
                img[(y * 64 + x) * 3 + 2],
            ]
        };
        assert_eq!(px(20, 25), [1.0, 1.0, 1.0], "peak cell must be white");
        let dim = px(60, 2);
        assert!(
            dim.iter().sum::<f32>() > 0.0 && dim.iter().sum::<f32>() < 1.0,
            "{dim:?}"
        );
        assert_eq!(px(5, 5), [0.0, 0.0, 0.0], "zero-pdf cell must be black");
        let o = crate::viz::rasterize_pdf(&t, 64, 64, true);
        assert_eq!(
            &o[(8 * 64 + 8) * 3..(8 * 64 + 8) * 3 + 3],
            &[0.0, 1.0, 0.0],
            "cell corner outlined"
        );
    }
}
