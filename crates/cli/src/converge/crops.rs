//! The noise figure: one crop of every method's image at equal time beside the reference's,
//! as path-guiding papers show it. The crop is where the methods differ most, or given.

use anyhow::{anyhow, bail, Result};
use plotters::prelude::*;

use super::metrics::{errors, pixel_relse, Image};

/// A rectangle of the image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Crop {
    pub x: u32,
    pub y: u32,
    pub w: u32,
    pub h: u32,
}

impl Crop {
    /// Parses `--crop X,Y,W,H` and checks it against the image size.
    pub fn parse(s: &str, width: u32, height: u32) -> Result<Crop> {
        let v: Vec<u32> = s
            .split(',')
            .map(|t| t.trim().parse::<u32>())
            .collect::<Result<_, _>>()
            .map_err(|_| anyhow!("--crop {s}: expected X,Y,W,H in pixels"))?;
        let [x, y, w, h] = v[..] else {
            bail!("--crop {s}: expected X,Y,W,H in pixels");
        };
        if w == 0
            || h == 0
            || x as u64 + w as u64 > width as u64
            || y as u64 + h as u64 > height as u64
        {
            bail!("--crop {s}: not a non-empty rectangle inside the {width}x{height} image");
        }
        Ok(Crop { x, y, w, h })
    }

    fn cut(&self, img: &Image) -> Image {
        let mut pixels = Vec::with_capacity((self.w * self.h) as usize);
        for y in self.y..self.y + self.h {
            let row = (y * img.width + self.x) as usize;
            pixels.extend_from_slice(&img.pixels[row..row + self.w as usize]);
        }
        Image {
            width: self.w,
            height: self.h,
            pixels,
        }
    }
}

/// The square crop (a quarter of the shorter side, at least 8 pixels) where the methods'
/// per-pixel errors differ most: the largest sum over the window of the spread (largest minus
/// smallest relative squared error among `images`).
pub fn where_methods_differ(images: &[&Image], reference: &Image) -> Crop {
    let (w, h) = (reference.width, reference.height);
    let side = (w.min(h) / 4).max(8).min(w).min(h);
    let spread: Vec<f64> = (0..reference.pixels.len())
        .map(|i| {
            let e = images
                .iter()
                .map(|im| pixel_relse(im.pixels[i], reference.pixels[i]));
            let (lo, hi) = e.fold((f64::INFINITY, 0.0f64), |(lo, hi), v| {
                (lo.min(v), hi.max(v))
            });
            if images.len() < 2 {
                hi
            } else {
                hi - lo
            }
        })
        .collect();
    // Summed-area table: window sums in O(1).
    let (wu, hu) = (w as usize, h as usize);
    let mut sat = vec![0.0f64; (wu + 1) * (hu + 1)];
    for y in 0..hu {
        for x in 0..wu {
            sat[(y + 1) * (wu + 1) + x + 1] =
                spread[y * wu + x] + sat[y * (wu + 1) + x + 1] + sat[(y + 1) * (wu + 1) + x]
                    - sat[y * (wu + 1) + x];
        }
    }
    let s = side as usize;
    let sum = |x: usize, y: usize| {
        sat[(y + s) * (wu + 1) + x + s] - sat[y * (wu + 1) + x + s] - sat[(y + s) * (wu + 1) + x]
            + sat[y * (wu + 1) + x]
    };
    let mut best = (f64::NEG_INFINITY, 0, 0);
    for y in 0..=hu - s {
        for x in 0..=wu - s {
            let v = sum(x, y);
            if v > best.0 {
                best = (v, x, y);
            }
        }
    }
    Crop {
        x: best.1 as u32,
        y: best.2 as u32,
        w: side,
        h: side,
    }
}

/// One panel of the figure.
pub struct Panel<'a> {
    pub label: String,
    pub image: &'a Image,
}

const LABEL_H: u32 = 40;
const GAP: u32 = 8;

/// The figure as PNG bytes: the reference's crop, then each panel's, magnified to about 200
/// pixels a side with nearest-neighbour pixels, each labelled with its name and the crop's
/// relMSE. All crops share one exposure (the reference crop's 99th percentile at 0.9).
pub fn figure(reference: &Image, panels: &[Panel], crop: Crop) -> Result<Vec<u8>> {
    super::plot::register_font();
    let zoom = (200 / crop.w.max(crop.h)).max(1);
    let (pw, ph) = (crop.w * zoom, crop.h * zoom);
    let n = panels.len() as u32 + 1;
    let (width, height) = (n * pw + (n + 1) * GAP, ph + LABEL_H + 2 * GAP);
    let mut rgb = vec![255u8; (width * height * 3) as usize];
    let ref_crop = crop.cut(reference);
    let scale = exposure(&ref_crop);
    let mut labels = vec![("reference".to_string(), String::new())];
    blit(
        &mut rgb,
        width,
        &ref_crop,
        zoom,
        scale,
        (GAP, GAP + LABEL_H),
    );
    for (i, p) in panels.iter().enumerate() {
        let c = crop.cut(p.image);
        let e = errors(&c, &ref_crop).relmse;
        let x = GAP + (i as u32 + 1) * (pw + GAP);
        blit(&mut rgb, width, &c, zoom, scale, (x, GAP + LABEL_H));
        labels.push((p.label.clone(), format!("relMSE {e:.3e}")));
    }
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (width, height)).into_drawing_area();
        let e = |e| anyhow!("drawing the crop figure: {e:?}");
        for (i, (name, err)) in labels.iter().enumerate() {
            let x = (GAP + i as u32 * (pw + GAP)) as i32;
            root.draw(&Text::new(name.clone(), (x, 4), ("sans-serif", 15)))
                .map_err(e)?;
            root.draw(&Text::new(err.clone(), (x, 22), ("sans-serif", 13)))
                .map_err(e)?;
        }
        root.present().map_err(e)?;
    }
    Ok(pathfarm_render::output::encode_png_rgb8(
        width, height, &rgb,
    )?)
}

/// The scale that puts the 99th percentile of `img`'s largest channel at 0.9.
fn exposure(img: &Image) -> f32 {
    let mut v: Vec<f32> = img
        .pixels
        .iter()
        .map(|p| p[0].max(p[1]).max(p[2]))
        .filter(|v| v.is_finite())
        .collect();
    v.sort_by(f32::total_cmp);
    let p99 = v.get(v.len() * 99 / 100).copied().unwrap_or(1.0);
    if p99 > 0.0 {
        0.9 / p99
    } else {
        1.0
    }
}

/// Copies `img` scaled by `scale` and magnified `zoom` times into `rgb` at `at`.
fn blit(rgb: &mut [u8], width: u32, img: &Image, zoom: u32, scale: f32, at: (u32, u32)) {
    for y in 0..img.height * zoom {
        for x in 0..img.width * zoom {
            let p = img.pixels[((y / zoom) * img.width + x / zoom) as usize];
            let o = (((at.1 + y) * width + at.0 + x) * 3) as usize;
            for c in 0..3 {
                let v = pathfarm_render::output::srgb_encode(p[c] * scale);
                rgb[o + c] = (v * 255.0 + 0.5) as u8;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(w: u32, h: u32, v: f32) -> Image {
        Image {
            width: w,
            height: h,
            pixels: vec![[v; 3]; (w * h) as usize],
        }
    }

    #[test]
    fn the_crop_lands_where_the_methods_disagree() {
        // Deterministic: two images equal to the reference except one, which is wrong in
        // a 10x10 block at (40, 24); the 16x16 crop must contain that block.
        let reference = flat(64, 64, 1.0);
        let good = reference.clone();
        let mut bad = reference.clone();
        for y in 24..34 {
            for x in 40..50 {
                bad.pixels[y * 64 + x] = [3.0; 3];
            }
        }
        let c = where_methods_differ(&[&good, &bad], &reference);
        assert_eq!((c.w, c.h), (16, 16));
        assert!(
            c.x <= 40 && c.x + 16 >= 50 && c.y <= 24 && c.y + 16 >= 34,
            "{c:?}"
        );
    }

    #[test]
    fn crops_are_parsed_and_checked_against_the_image() {
        assert_eq!(
            Crop::parse("1,2,3,4", 10, 10).unwrap(),
            Crop {
                x: 1,
                y: 2,
                w: 3,
                h: 4
            }
        );
        for bad in ["1,2,3", "0,0,0,4", "8,0,3,3", "a,b,c,d"] {
            assert!(Crop::parse(bad, 10, 10).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_figure_has_a_panel_per_method_and_the_reference() {
        let reference = flat(32, 32, 0.5);
        let noisy = flat(32, 32, 0.6);
        let panels = [Panel {
            label: "path".into(),
            image: &noisy,
        }];
        let crop = Crop {
            x: 0,
            y: 0,
            w: 20,
            h: 20,
        };
        let png = figure(&reference, &panels, crop).unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        // 2 panels of 20 x 10 = 200 pixels, 3 gaps of 8.
        assert_eq!(
            img.dimensions(),
            (2 * 200 + 3 * GAP, 200 + LABEL_H + 2 * GAP)
        );
        // The second panel is brighter than the first (0.6 against 0.5 at one exposure).
        let at = |x: u32| img.get_pixel(x, GAP + LABEL_H + 100).0[0];
        assert!(at(GAP + 200 + GAP + 100) > at(GAP + 100));
    }
}
