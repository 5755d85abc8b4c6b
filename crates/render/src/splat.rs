//! Phase 2 of rendering: samples splatted into pixel sums by gathering. A pixel gathers, in
//! a fixed order (source pixel, then sample index), the samples within its filter's reach,
//! so its sums do not depend on who rendered the samples or in which order they arrived:
//! [`crate::render_region_into`] gathers a region's pixels from the samples of the region
//! and its halo, and a [`UnitSplat`] gathers a whole image from samples that arrive region by
//! region (the farm's units of few samples per pixel), the same bits either way.

use std::sync::Arc;

use glam::Vec2;
use rayon::prelude::*;

use crate::film::{Accumulator, Film, PixelStats};
use crate::filter::Filter;
use crate::render::{Region, RenderSettings};

mod plan;
mod unit_film;

pub use plan::{RegionSplat, SplatPlan};
pub use unit_film::UnitFilm;

/// One camera sample, kept until it has been splatted: its film position
/// within its pixel and its radiance estimate.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
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

/// Who does a splat's work (the film is the same either way).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Threads {
    /// The rayon pool, rows and runs of samples as work items: a whole image's pass.
    Pool,
    /// The calling thread alone: a farm tile prepared beside other uploads, or a unit's
    /// thin bands, where handing work to the pool costs more than the work.
    Caller,
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
    /// Whether the rayon pool shares the work (neither changes the film).
    pub(crate) threads: Threads,
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
        let weigh = |(out, recs): (&mut [f32], &[SampleRec])| {
            for (wt, rec) in out.chunks_mut(2 * span).zip(recs) {
                axis_weights(&filter, reach, rec.offset, wt);
            }
        };
        match self.threads {
            Threads::Pool => (weights.par_chunks_mut(tile * n * 2 * span))
                .zip(self.buffer.par_chunks(tile * n))
                .for_each(weigh),
            Threads::Caller => weigh((weights, self.buffer)),
        }
        let (buf, wts) = (self.buffer, &*weights);
        let (region, halo) = (self.region, self.halo);
        let (h, hw) = (self.size.1 as i32, halo.width() as usize);
        let w = self.size.0 as i32;
        let fw = film_region.width() as usize;
        let (dx, dy) = (
            (region.x0 - film_region.x0) as usize,
            (region.y0 - film_region.y0) as usize,
        );
        let stride = 2 * span;
        // Pixel x's sums: the samples of its filter footprint in its order (rows, then
        // columns, then sample index).
        let gather = |x: i32, y: i32, pixel: &mut PixelStats| {
            pixel.count += n as u32;
            let mut acc = Accumulator::of(pixel);
            for qy in (y - reach).max(0)..=(y + reach).min(h - 1) {
                let ky = span + (y - qy + reach) as usize;
                let row_q = (qy - halo.y0 as i32) as usize * hw;
                for qx in (x - reach).max(0)..=(x + reach).min(w - 1) {
                    let kx = (x - qx + reach) as usize;
                    let q = row_q + (qx - halo.x0 as i32) as usize;
                    for k in q * n..(q + 1) * n {
                        let wt = &wts[k * stride..(k + 1) * stride];
                        // Added even at weight zero (it adds exact zeros: the sums are
                        // unchanged), which is cheaper than a branch that the random
                        // sample positions make unpredictable.
                        acc.add(wt[kx] * wt[ky], buf[k].value);
                    }
                }
            }
            acc.store(pixel);
        };
        // Pixels x and x + 1 together, each in its own order as `gather` adds (so the same
        // bits): two independent chains of additions, which the CPU overlaps where one
        // pixel's chain waits on each addition's latency, reading the same samples (13 %
        // less time for a 1920x1080 unit's prepare than one pixel at a time; four at a time
        // gained less).
        let gather_pair = |x: i32, y: i32, (p0, p1): (&mut PixelStats, &mut PixelStats)| {
            p0.count += n as u32;
            p1.count += n as u32;
            let (mut a0, mut a1) = (Accumulator::of(p0), Accumulator::of(p1));
            let (lo0, hi0) = ((x - reach).max(0), (x + reach).min(w - 1));
            let (lo1, hi1) = ((x + 1 - reach).max(0), (x + 1 + reach).min(w - 1));
            for qy in (y - reach).max(0)..=(y + reach).min(h - 1) {
                let ky = span + (y - qy + reach) as usize;
                let row_q = (qy - halo.y0 as i32) as usize * hw;
                for qx in lo0..=hi1 {
                    // pixel x's column weight where it reaches qx; x + 1's is the next
                    // (where only x + 1 reaches qx, x's index is -1: wraps, never read)
                    let kx = (x - qx + reach) as usize;
                    let q = row_q + (qx - halo.x0 as i32) as usize;
                    let (to0, to1) = (qx <= hi0, qx >= lo1);
                    for k in q * n..(q + 1) * n {
                        let wt = &wts[k * stride..(k + 1) * stride];
                        let v = buf[k].value;
                        if to0 {
                            a0.add(wt[kx] * wt[ky], v);
                        }
                        if to1 {
                            a1.add(wt[kx.wrapping_add(1)] * wt[ky], v);
                        }
                    }
                }
            }
            a0.store(p0);
            a1.store(p1);
        };
        let gather_row = |(row, line): (usize, &mut [PixelStats])| {
            let y = region.y0 as i32 + row as i32;
            let pixels = &mut line[dx..dx + region.width() as usize];
            let mut pairs = pixels.chunks_exact_mut(2);
            let mut x = region.x0 as i32;
            for pair in &mut pairs {
                let (p0, p1) = pair.split_at_mut(1);
                gather_pair(x, y, (&mut p0[0], &mut p1[0]));
                x += 2;
            }
            if let [last] = pairs.into_remainder() {
                gather(x, y, last);
            }
        };
        let rows = region.height() as usize;
        match self.threads {
            Threads::Pool => (film.pixels.par_chunks_mut(fw).skip(dy).take(rows))
                .enumerate()
                .for_each(gather_row),
            Threads::Caller => (film.pixels.chunks_mut(fw).skip(dy).take(rows))
                .enumerate()
                .for_each(gather_row),
        }
    }
}

/// A whole image's film from samples that arrive region by region ([`crate::sample_region`]
/// of disjoint regions covering the image), equal bit for bit to what
/// [`crate::render_region_into`] of the whole image splats from the same samples: each
/// render call's samples are splatted in the same passes, and every pixel gathers the same
/// samples in the same order. A region's pixels whose filter reaches no other region are
/// gathered as soon as it arrives ([`UnitSplat::add`], or apart by [`SplatPlan::prepare`]
/// and put in place by [`UnitSplat::add_prepared`]); the rest, a band `reach` pixels wide
/// along its edges inside the image, once every region is in ([`UnitSplat::finish`]).
#[derive(Clone)]
pub struct UnitSplat {
    plan: SplatPlan,
    /// Per splat pass of the plan: its `n` records a pixel, the image row-major (filled in
    /// as regions arrive).
    recs: Vec<Vec<SampleRec>>,
    film: Film,
    /// The interiors of prepared regions, kept in their own films (not copied into `film`).
    interiors: Vec<(Region, Arc<Film>)>,
    /// Interiors merged already ([`UnitSplat::merge_interiors`]).
    merged: Vec<Region>,
    weights: Vec<f32>,
}

impl std::fmt::Debug for UnitSplat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UnitSplat")
            .field("size", &self.plan.size)
            .field("spp", &self.plan.spp)
            .field("passes", &self.plan.passes.len())
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
            plan: SplatPlan::new(filter, size, (settings, spp), first_samples),
            recs: Vec::new(),
            film: Film::new(size.0, size.1),
            interiors: Vec::new(),
            merged: Vec::new(),
            weights: Vec::new(),
        };
        s.size_buffers(Vec::new());
        s
    }

    /// This splat made the splat of another unit of the same image, filter and seed (as
    /// [`UnitSplat::new`] would make it), into `film` (of the image's size, whatever its
    /// pixels hold: every pixel is overwritten, by a region's interior or by a band gathered
    /// into zeros, or held apart with its prepared region): its buffers are reused (a unit's
    /// are tens of megabytes, faulted in again if allocated anew for every unit, and zeroing
    /// them cost as much as splatting).
    pub fn reuse(
        &mut self,
        (settings, spp): (&RenderSettings, u32),
        first_samples: &[u64],
        film: Film,
    ) {
        assert_eq!((film.width, film.height), self.plan.size);
        self.film = film;
        self.interiors.clear();
        self.merged.clear();
        let (filter, size) = (self.plan.filter, self.plan.size);
        self.plan = SplatPlan::new(filter, size, (settings, spp), first_samples);
        let old = std::mem::take(&mut self.recs);
        self.size_buffers(old);
    }

    /// The sample records of the plan's passes, from `old` buffers where there are some.
    fn size_buffers(&mut self, old: Vec<Vec<SampleRec>>) {
        let npix = self.plan.size.0 as usize * self.plan.size.1 as usize;
        let mut old = old.into_iter();
        for pass in &self.plan.passes {
            let mut recs = old.next().unwrap_or_default();
            // every record is written by `add` before it is read (the regions cover the
            // image): no need to clear reused ones
            recs.resize(npix * pass.n as usize, SampleRec::default());
            self.recs.push(recs);
        }
    }

    /// How this unit's samples are splatted: what preparing a region apart needs.
    pub fn plan(&self) -> &SplatPlan {
        &self.plan
    }

    /// The samples of `region`: for each render call, every pixel of the region row-major,
    /// its `spp` samples in index order (`values.len()` must be that). Gathers the region's
    /// pixels whose filter reaches no other region, with the rayon pool (a one-process
    /// render adds the whole image at once).
    pub fn add(&mut self, region: Region, values: &[glam::Vec3]) {
        let full = Region::full(self.plan.size.0, self.plan.size.1);
        self.plan
            .write_records(region, values, (&mut self.recs, full));
        if let Some(inner) = self.plan.interior(region) {
            // (a reused film holds an earlier unit's pixels)
            zero_rows(&mut self.film, inner);
            let target = Target {
                region: inner,
                film: &mut self.film,
                film_region: full,
            };
            let recs = (&self.recs[..], full);
            gather(&self.plan, recs, target, &mut self.weights, Threads::Pool);
        }
    }

    /// A region [`SplatPlan::prepare`]d with this unit's plan (it panics otherwise): the
    /// samples its own and its neighbours' bands will be gathered from put in place, and its
    /// gathered interior kept (shared, not copied: [`UnitFilm`]). Its interior's pixels are
    /// gathered nowhere else.
    pub fn add_prepared(&mut self, r: &RegionSplat) {
        assert_eq!(r.plan, self.plan, "a region prepared for another unit");
        let (w, region) = (self.plan.size.0 as usize, r.region);
        // A band pixel reads samples within the filter's reach, so no band of this unit reads
        // a sample deeper than twice the reach inside a region's edges (image edges aside).
        let deep = self
            .plan
            .interior(region)
            .and_then(|i| self.plan.interior(i));
        let rw = region.width() as usize;
        for ((dst, src), pass) in self.recs.iter_mut().zip(&r.recs).zip(&self.plan.passes) {
            let n = pass.n as usize;
            for band in bands(region, deep) {
                let bw = band.width() as usize * n;
                for y in band.y0 as usize..band.y1 as usize {
                    let at = ((y - region.y0 as usize) * rw + (band.x0 - region.x0) as usize) * n;
                    let start = (y * w + band.x0 as usize) * n;
                    dst[start..start + bw].copy_from_slice(&src[at..at + bw]);
                }
            }
        }
        if let Some(interior) = &r.interior {
            self.interiors.push(interior.clone());
        }
    }

    /// Merges the interiors of the regions prepared so far into `dst` (a whole-image film)
    /// and lets them go: for a unit whose film would be merged into `dst` when it ends, and
    /// whose pixels come after everything else `dst` will take (its iteration's earlier units
    /// ended), merging them now gives the same sums, as the tiles come in rather than all at
    /// the unit's end.
    pub fn merge_interiors(&mut self, dst: &mut Film) {
        assert_eq!((dst.width, dst.height), self.plan.size);
        for (r, f) in self.interiors.drain(..) {
            unit_film::merge_region(dst, r, &f);
            self.merged.push(r);
        }
    }

    /// The film, once every region of the image was added: the pixels `add` left (those
    /// within the filter's reach of another of `regions`) gathered now.
    pub fn finish(&mut self, regions: &[Region]) -> UnitFilm {
        let full = Region::full(self.plan.size.0, self.plan.size.1);
        for &r in regions {
            let inner = self.plan.interior(r);
            for band in bands(r, inner) {
                // (a reused film holds an earlier unit's pixels: the bands are gathered into
                // zeros, the interiors were copied over)
                zero_rows(&mut self.film, band);
                let target = Target {
                    region: band,
                    film: &mut self.film,
                    film_region: full,
                };
                let recs = (&self.recs[..], full);
                gather(&self.plan, recs, target, &mut self.weights, Threads::Caller);
            }
        }
        UnitFilm {
            film: std::mem::replace(&mut self.film, Film::new(0, 0)),
            interiors: std::mem::take(&mut self.interiors),
            merged: std::mem::take(&mut self.merged),
        }
    }
}

/// Sets the pixels of `r` of the whole-image `film` to zero.
fn zero_rows(film: &mut Film, r: Region) {
    let (w, rw) = (film.width as usize, r.width() as usize);
    for y in r.y0 as usize..r.y1 as usize {
        let start = y * w + r.x0 as usize;
        film.pixels[start..start + rw].fill(Default::default());
    }
}

/// Where a gather writes: the pixels of `region`, in `film`, which covers `film_region`.
struct Target<'a> {
    region: Region,
    film: &'a mut Film,
    film_region: Region,
}

/// Gathers the pixels of `target.region` in every pass of `plan`, in pass order, from the
/// sample records `recs` (per pass, `n` a pixel, `layout`'s pixels row-major; `layout` holds
/// the target's filter halo).
fn gather(
    plan: &SplatPlan,
    (recs, layout): (&[Vec<SampleRec>], Region),
    target: Target,
    weights: &mut Vec<f32>,
    threads: Threads,
) {
    let reach = plan.filter.reach() as u32;
    let (w, h) = plan.size;
    let halo = target.region.grown(reach, w, h);
    let lw = layout.width() as usize;
    let mut copied = Vec::new();
    for (pass, recs) in plan.passes.iter().zip(recs) {
        let n = pass.n as usize;
        // (a prepared region's interior reads its whole layout: no copy)
        let buffer: &[SampleRec] = if halo == layout {
            recs
        } else {
            copied.clear();
            for y in halo.y0..halo.y1 {
                let row = (y - layout.y0) as usize * lw;
                let a = row + (halo.x0 - layout.x0) as usize;
                let b = row + (halo.x1 - layout.x0) as usize;
                copied.extend_from_slice(&recs[a * n..b * n]);
            }
            &copied
        };
        let splat = Splat {
            filter: &plan.filter,
            size: plan.size,
            region: target.region,
            halo,
            tile: crate::render::DEFAULT_TILE as usize,
            threads,
            buffer,
        };
        splat.add_to(n, weights, target.film, target.film_region);
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
    use crate::rng::Rng;

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
