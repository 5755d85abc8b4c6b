//! Phase 2 of rendering: samples splatted into pixel sums by gathering. A pixel gathers, in
//! a fixed order (source pixel, then sample index), the samples within its filter's reach,
//! so its sums do not depend on who rendered the samples or in which order they arrived:
//! [`crate::render_region_into`] gathers a region's pixels from the samples of the region
//! and its halo, and a [`UnitSplat`] gathers a whole image from samples that arrive region by
//! region (the farm's units of few samples per pixel), the same bits either way.

use glam::Vec2;
use rayon::prelude::*;

use crate::film::Film;
use crate::filter::Filter;
use crate::render::{pass_ranges, Region, RenderSettings};
use crate::rng::Rng;

/// One camera sample, kept until it has been splatted: its film position
/// within its pixel and its radiance estimate.
#[derive(Clone, Copy, Default)]
pub(crate) struct SampleRec {
    pub(crate) offset: Vec2,
    pub(crate) value: glam::Vec3,
}

/// The filter weights of a sample at `offset` in its pixel `(qx, qy)` towards the pixels
/// `(qx - reach + k, ...)`: `out[k]` along x and `out[span + k]` along y, `span = 2 reach + 1`.
/// The offset from a target pixel's centre is `(qx - px) - 0.5 + offset`, which is exactly the
/// `q - (p + 0.5) + offset` of a per-pair evaluation (small integers and halves are exact in
/// f32), so the weights are the same bits.
#[inline]
pub(crate) fn axis_weights(filter: &Filter, reach: i32, offset: Vec2, out: &mut [f32]) {
    let span = 2 * reach as usize + 1;
    for k in 0..span {
        // target p = q - reach + k, so q - p = reach - k
        let base = (reach - k as i32) as f32 - 0.5;
        out[k] = filter.eval(base + offset.x);
        out[span + k] = filter.eval(base + offset.y);
    }
}

/// One pass's samples of `halo`'s pixels (`n` a pixel, in `buffer`), to be gathered into the
/// pixels of `region` (inside `halo`) of a `size` image.
pub(crate) struct Splat<'a> {
    pub(crate) filter: &'a Filter,
    pub(crate) size: (u32, u32),
    pub(crate) region: Region,
    pub(crate) halo: Region,
    /// Pixels per parallel work item (does not change the film).
    pub(crate) tile: usize,
    pub(crate) buffer: &'a [SampleRec],
}

impl Splat<'_> {
    /// Adds the samples to the pixels of `region` in `film`, which covers `film_region` (a
    /// region containing `region`); `weights` is scratch space. The filter is separable:
    /// each sample's weights along x and y towards the 2 reach + 1 pixel columns and rows it
    /// can reach are evaluated once (`axis_weights`), not once per target pixel (a
    /// gaussian's 5x5 footprint evaluated per pair cost 5x the exponentials; door-ajar path
    /// tracing spent about a quarter of its time here). Same operands as a per-pair
    /// evaluation, so the same bits.
    pub(crate) fn add_to(
        &self,
        n: usize,
        weights: &mut Vec<f32>,
        film: &mut Film,
        film_region: Region,
    ) {
        let tile = self.tile;
        let filter = *self.filter;
        let reach = filter.reach();
        let span = 2 * reach as usize + 1;
        // (every entry is written below: resizing keeps old values instead of zeroing)
        weights.resize(self.halo.pixels() * n * 2 * span, 0.0);
        weights
            .par_chunks_mut(tile * n * 2 * span)
            .zip(self.buffer.par_chunks(tile * n))
            .for_each(|(out, recs)| {
                for (wt, rec) in out.chunks_mut(2 * span).zip(recs) {
                    axis_weights(&filter, reach, rec.offset, wt);
                }
            });
        let (buf, wts) = (self.buffer, &*weights);
        let (region, halo) = (self.region, self.halo);
        let (h, hw) = (self.size.1 as i32, halo.width() as usize);
        let w = self.size.0 as i32;
        let fw = film_region.width() as usize;
        let (dx, dy) = (
            (region.x0 - film_region.x0) as usize,
            (region.y0 - film_region.y0) as usize,
        );
        film.pixels
            .par_chunks_mut(fw)
            .skip(dy)
            .take(region.height() as usize)
            .enumerate()
            .for_each(|(row, line)| {
                let y = region.y0 as i32 + row as i32;
                let pixels = &mut line[dx..dx + region.width() as usize];
                for (i, stats) in pixels.iter_mut().enumerate() {
                    let x = region.x0 as i32 + i as i32;
                    stats.count += n as u32;
                    for qy in (y - reach).max(0)..=(y + reach).min(h - 1) {
                        let ky = span + (y - qy + reach) as usize;
                        let row_q = (qy - halo.y0 as i32) as usize * hw;
                        for qx in (x - reach).max(0)..=(x + reach).min(w - 1) {
                            let kx = (x - qx + reach) as usize;
                            let q = row_q + (qx - halo.x0 as i32) as usize;
                            let recs = &buf[q * n..(q + 1) * n];
                            let ws = wts[q * n * 2 * span..(q + 1) * n * 2 * span]
                                .chunks_exact(2 * span);
                            for (rec, wt) in recs.iter().zip(ws) {
                                // Added even at weight zero (it adds exact zeros: the sums
                                // are unchanged), which is cheaper than a branch that the
                                // random sample positions make unpredictable.
                                stats.add(wt[kx] * wt[ky], rec.value);
                            }
                        }
                    }
                }
            });
    }
}

/// One splat pass of a [`UnitSplat`]: its samples `s0..s0 + n` of a render call whose
/// first random stream is `first_sample`, for every pixel of the image.
#[derive(Clone)]
struct UnitPass {
    call: usize,
    first_sample: u64,
    s0: u32,
    n: u32,
    /// `n` records a pixel, the image row-major (filled in as regions arrive).
    recs: Vec<SampleRec>,
}

/// A whole image's film from samples that arrive region by region ([`crate::sample_region`]
/// of disjoint regions covering the image), equal bit for bit to what
/// [`crate::render_region_into`] of the whole image splats from the same samples: each
/// render call's samples are splatted in the same passes, and every pixel gathers the same
/// samples in the same order. A region's pixels whose filter reaches no other region are
/// gathered as soon as it arrives ([`UnitSplat::add`]); the rest, a band `reach` pixels wide
/// along its edges inside the image, once every region is in ([`UnitSplat::finish`]).
#[derive(Clone)]
pub struct UnitSplat {
    filter: Filter,
    size: (u32, u32),
    seed: u64,
    /// Samples per pixel of each render call (the calls' random streams follow
    /// `first_samples`).
    spp: u32,
    passes: Vec<UnitPass>,
    film: Film,
    weights: Vec<f32>,
}

impl std::fmt::Debug for UnitSplat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UnitSplat")
            .field("size", &self.size)
            .field("spp", &self.spp)
            .field("passes", &self.passes.len())
            .finish_non_exhaustive()
    }
}

impl UnitSplat {
    /// The splat of a unit of a `size` image whose render calls `c` drew `spp` samples per
    /// pixel from random stream `first_samples[c]` on, with `filter` and the job's `seed`,
    /// splatting as `settings`' pass sizes say (its `spp` is ignored).
    pub fn new(
        filter: Filter,
        size: (u32, u32),
        (settings, spp): (&RenderSettings, u32),
        first_samples: &[u64],
    ) -> Self {
        let mut s = UnitSplat {
            filter,
            size,
            seed: settings.seed,
            spp,
            passes: Vec::new(),
            film: Film::new(size.0, size.1),
            weights: Vec::new(),
        };
        s.plan((settings, spp), first_samples);
        s
    }

    /// This splat made the splat of another unit of the same image, filter and seed (as
    /// [`UnitSplat::new`] would make it), into `film` (all zero, of the image's size): its
    /// buffers are reused (a unit's are tens of megabytes, faulted in again if allocated
    /// anew for every unit).
    pub fn reuse(
        &mut self,
        (settings, spp): (&RenderSettings, u32),
        first_samples: &[u64],
        film: Film,
    ) {
        assert_eq!((film.width, film.height), self.size);
        self.film = film;
        self.seed = settings.seed;
        self.spp = spp;
        self.plan((settings, spp), first_samples);
    }

    /// The passes of the unit's render calls, their buffers (reused where there are some)
    /// the image's size.
    fn plan(&mut self, (settings, spp): (&RenderSettings, u32), first_samples: &[u64]) {
        let (w, h) = self.size;
        let npix = w as usize * h as usize;
        let ranges = pass_ranges(w, h, settings, spp);
        let mut old = std::mem::take(&mut self.passes).into_iter();
        for (call, &first_sample) in first_samples.iter().enumerate() {
            for &(s0, s1) in &ranges {
                let mut recs = old.next().map(|p| p.recs).unwrap_or_default();
                // every record is written by `add` before it is read (the regions cover the
                // image): no need to clear reused ones
                recs.resize(npix * (s1 - s0) as usize, SampleRec::default());
                self.passes.push(UnitPass {
                    call,
                    first_sample,
                    s0,
                    n: s1 - s0,
                    recs,
                });
            }
        }
    }

    /// The samples of `region`: for each render call, every pixel of the region row-major,
    /// its `spp` samples in index order (`values.len()` must be that). Gathers the region's
    /// pixels whose filter reaches no other region.
    pub fn add(&mut self, region: Region, values: &[glam::Vec3]) {
        let (w, spp) = (self.size.0 as usize, self.spp as usize);
        let per_call = region.pixels() * spp;
        assert_eq!(values.len(), per_call * self.calls(), "{region:?}");
        let (rw, seed) = (region.width() as usize, self.seed);
        for pass in &mut self.passes {
            let (n, s0) = (pass.n as usize, pass.s0 as usize);
            let call = &values[pass.call * per_call..(pass.call + 1) * per_call];
            for (i, px) in call.chunks_exact(spp).enumerate() {
                let (x, y) = (region.x0 as usize + i % rw, region.y0 as usize + i / rw);
                let pixel = y * w + x;
                let recs = &mut pass.recs[pixel * n..(pixel + 1) * n];
                for (k, rec) in recs.iter_mut().enumerate() {
                    let index = pass.first_sample + (s0 + k) as u64;
                    rec.offset = Rng::for_sample(seed, pixel as u64, index).next_2d();
                    rec.value = px[s0 + k];
                }
            }
        }
        if let Some(inner) = self.interior(region) {
            self.gather(inner);
        }
    }

    /// The film, once every region of the image was added: the pixels `add` left (those
    /// within the filter's reach of another of `regions`) gathered now.
    pub fn finish(&mut self, regions: &[Region]) -> Film {
        for &r in regions {
            let inner = self.interior(r);
            for band in bands(r, inner) {
                self.gather(band);
            }
        }
        std::mem::replace(&mut self.film, Film::new(0, 0))
    }

    fn calls(&self) -> usize {
        self.passes.last().map_or(0, |p| p.call + 1)
    }

    /// The pixels of `r` whose filter (clipped to the image) reaches no pixel outside `r`.
    fn interior(&self, r: Region) -> Option<Region> {
        let reach = self.filter.reach() as u32;
        let (w, h) = self.size;
        let lo = |a: u32| if a == 0 { 0 } else { a + reach };
        let hi = |b: u32, end: u32| {
            if b == end {
                end
            } else {
                b.saturating_sub(reach)
            }
        };
        let inner = Region {
            x0: lo(r.x0),
            y0: lo(r.y0),
            x1: hi(r.x1, w),
            y1: hi(r.y1, h),
        };
        (inner.x0 < inner.x1 && inner.y0 < inner.y1).then_some(inner)
    }

    /// Gathers the pixels of `target` in every pass, in pass order.
    fn gather(&mut self, target: Region) {
        let reach = self.filter.reach() as u32;
        let (w, h) = self.size;
        let halo = target.grown(reach, w, h);
        let full = Region::full(w, h);
        let mut buffer = Vec::new();
        for pass in &self.passes {
            let n = pass.n as usize;
            buffer.clear();
            for y in halo.y0..halo.y1 {
                let row = y as usize * w as usize;
                let (a, b) = (row + halo.x0 as usize, row + halo.x1 as usize);
                buffer.extend_from_slice(&pass.recs[a * n..b * n]);
            }
            let splat = Splat {
                filter: &self.filter,
                size: self.size,
                region: target,
                halo,
                tile: crate::render::DEFAULT_TILE as usize,
                buffer: &buffer,
            };
            splat.add_to(n, &mut self.weights, &mut self.film, full);
        }
    }
}

/// `r` less `inner` (a region inside it, or none): up to four bands, top, bottom, left,
/// right.
fn bands(r: Region, inner: Option<Region>) -> Vec<Region> {
    let Some(i) = inner else {
        return vec![r];
    };
    let bands = [
        Region { y1: i.y0, ..r },
        Region { y0: i.y1, ..r },
        Region {
            x1: i.x0,
            y0: i.y0,
            y1: i.y1,
            ..r
        },
        Region {
            x0: i.x1,
            y0: i.y0,
            y1: i.y1,
            ..r
        },
    ];
    bands
        .into_iter()
        .filter(|b| b.x0 < b.x1 && b.y0 < b.y1)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn separable_splat_weights_equal_the_per_pair_filter_bits() {
        // Deterministic identity (no significance level): for every filter, random sample
        // offsets and every (source, target) pixel pair in reach, the product of the
        // precomputed axis weights is bit for bit the per-pair `eval(d.x) * eval(d.y)`.
        let filters = [
            Filter::Box { radius: 0.5 },
            Filter::Box { radius: 1.5 },
            Filter::Tent { radius: 1.0 },
            Filter::Tent { radius: 2.5 },
            Filter::Gaussian { stddev: 0.5 },
            Filter::Gaussian { stddev: 0.8 },
        ];
        let mut rng = Rng::new(31, 7);
        let mut nonzero = 0;
        for filter in filters {
            let reach = filter.reach();
            let span = 2 * reach as usize + 1;
            let mut wt = vec![0.0f32; 2 * span];
            for _ in 0..500 {
                let offset = rng.next_2d();
                let (qx, qy) = (7i32, 9i32);
                axis_weights(&filter, reach, offset, &mut wt);
                for py in qy - reach..=qy + reach {
                    for px in qx - reach..=qx + reach {
                        let centre = Vec2::new(px as f32 + 0.5, py as f32 + 0.5);
                        let d = Vec2::new(qx as f32, qy as f32) - centre + offset;
                        let per_pair = filter.eval(d.x) * filter.eval(d.y);
                        let (kx, ky) = ((px - qx + reach) as usize, (py - qy + reach) as usize);
                        let separable = wt[kx] * wt[span + ky];
                        assert_eq!(separable.to_bits(), per_pair.to_bits(), "{filter:?}");
                        nonzero += (per_pair != 0.0) as u32;
                    }
                }
            }
        }
        assert!(nonzero > 10_000, "weights must not all vanish ({nonzero})");
    }
}
