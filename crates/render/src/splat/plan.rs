//! A unit's splat plan, and a region's samples prepared by it apart from the unit's film:
//! the film positions drawn and the region's interior gathered, which is most of a unit's
//! splatting, done where its owner's lock is not held (a farm coordinator prepares several
//! uploads at once, then only copies them in).

use glam::Vec3;

use super::{gather, SampleRec, Target, Threads};
use crate::film::Film;
use crate::filter::Filter;
use crate::render::{pass_ranges, Region, RenderSettings};
use crate::rng::Rng;

/// One splat pass of a unit: its samples `s0..s0 + n` of a render call whose first random
/// stream is `first_sample`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct PassPlan {
    pub(crate) call: usize,
    pub(crate) first_sample: u64,
    pub(crate) s0: u32,
    pub(crate) n: u32,
}

/// How a unit's samples are splatted: the image, the filter, the job's seed and the unit's
/// splat passes. Small (a few passes); a [`crate::UnitSplat`] has one
/// ([`crate::UnitSplat::plan`]).
#[derive(Clone, Debug, PartialEq)]
pub struct SplatPlan {
    pub(crate) filter: Filter,
    pub(crate) size: (u32, u32),
    pub(crate) seed: u64,
    /// Samples per pixel of each render call.
    pub(crate) spp: u32,
    pub(crate) passes: Vec<PassPlan>,
}

impl SplatPlan {
    /// The plan of a unit of a `size` image whose render calls `c` drew `spp` samples per
    /// pixel from random stream `first_samples[c]` on, splatted as `settings`' pass sizes
    /// say (its `spp` is ignored).
    pub(crate) fn new(
        filter: Filter,
        size: (u32, u32),
        (settings, spp): (&RenderSettings, u32),
        first_samples: &[u64],
    ) -> Self {
        let ranges = pass_ranges(size.0, size.1, settings, spp);
        let passes = (first_samples.iter().enumerate())
            .flat_map(|(call, &first_sample)| {
                ranges.iter().map(move |&(s0, s1)| PassPlan {
                    call,
                    first_sample,
                    s0,
                    n: s1 - s0,
                })
            })
            .collect();
        SplatPlan {
            filter,
            size,
            seed: settings.seed,
            spp,
            passes,
        }
    }

    fn calls(&self) -> usize {
        self.passes.last().map_or(0, |p| p.call + 1)
    }

    /// The samples `region` holds: its pixels times the samples of every render call.
    pub fn samples(&self, region: Region) -> usize {
        region.pixels() * self.spp as usize * self.calls()
    }

    /// The samples of `region` (for each render call, every pixel of the region row-major,
    /// its `spp` samples in index order; `values.len()` must be [`SplatPlan::samples`]),
    /// with their film positions, and its pixels whose filter reaches no other region
    /// gathered: what [`crate::UnitSplat::add_prepared`] puts in place.
    ///
    /// On the calling thread alone: a farm coordinator prepares several uploads side by
    /// side, and a tile's work is less than handing it to the rayon pool costs.
    pub fn prepare(&self, region: Region, values: &[Vec3]) -> RegionSplat {
        let mut recs: Vec<Vec<SampleRec>> = (self.passes.iter())
            .map(|pass| vec![SampleRec::default(); region.pixels() * pass.n as usize])
            .collect();
        self.write_records(region, values, (&mut recs, region));
        let interior = self.interior(region).map(|inner| {
            let mut film = Film::new(inner.width(), inner.height());
            let target = Target {
                region: inner,
                film: &mut film,
                film_region: inner,
            };
            gather(
                self,
                (&recs, region),
                target,
                &mut Vec::new(),
                Threads::Caller,
            );
            (inner, std::sync::Arc::new(film))
        });
        RegionSplat {
            plan: self.clone(),
            region,
            recs,
            interior,
        }
    }

    /// Writes the sample records of `region` (its `values`, as [`SplatPlan::prepare`] takes
    /// them) into `recs` (per pass, `n` records a pixel, `layout`'s pixels row-major;
    /// `layout` contains `region`).
    pub(crate) fn write_records(
        &self,
        region: Region,
        values: &[Vec3],
        (recs, layout): (&mut [Vec<SampleRec>], Region),
    ) {
        assert_eq!(values.len(), self.samples(region), "{region:?}");
        let per_call = region.pixels() * self.spp as usize;
        let (w, rw, lw) = (
            self.size.0 as usize,
            region.width() as usize,
            layout.width() as usize,
        );
        for (pass, dst) in self.passes.iter().zip(recs) {
            let call = &values[pass.call * per_call..(pass.call + 1) * per_call];
            let (n, s0) = (pass.n as usize, pass.s0 as usize);
            for (i, px) in call.chunks_exact(self.spp as usize).enumerate() {
                let (x, y) = (region.x0 as usize + i % rw, region.y0 as usize + i / rw);
                let pixel = (y * w + x) as u64;
                let at = (y - layout.y0 as usize) * lw + (x - layout.x0 as usize);
                let out = &mut dst[at * n..(at + 1) * n];
                for (k, (rec, &value)) in out.iter_mut().zip(&px[s0..s0 + n]).enumerate() {
                    let index = pass.first_sample + (s0 + k) as u64;
                    let offset = Rng::for_sample(self.seed, pixel, index).next_2d();
                    *rec = SampleRec { offset, value };
                }
            }
        }
    }

    /// The pixels of `r` whose filter (clipped to the image) reaches no pixel outside `r`.
    pub(crate) fn interior(&self, r: Region) -> Option<Region> {
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
}

/// A region's samples with their film positions, and its interior gathered, by one unit's
/// [`SplatPlan`] ([`SplatPlan::prepare`]).
#[derive(Clone, PartialEq)]
pub struct RegionSplat {
    pub(crate) plan: SplatPlan,
    pub(crate) region: Region,
    /// Per splat pass of the plan: `n` records a pixel, the region row-major.
    pub(crate) recs: Vec<Vec<SampleRec>>,
    /// The interior and its pixels (an interior-sized film), if it has any.
    pub(crate) interior: Option<(Region, std::sync::Arc<Film>)>,
}

impl std::fmt::Debug for RegionSplat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RegionSplat")
            .field("region", &self.region)
            .field("samples", &self.recs.iter().map(Vec::len).sum::<usize>())
            .field("interior", &self.interior.as_ref().map(|(r, _)| *r))
            .finish_non_exhaustive()
    }
}

impl RegionSplat {
    /// The region it holds.
    pub fn region(&self) -> Region {
        self.region
    }

    /// The plan it was prepared by.
    pub fn plan(&self) -> &SplatPlan {
        &self.plan
    }

    /// The radiance values it was prepared from, in their order (for each render call, every
    /// pixel of the region row-major, its samples in index order).
    pub fn values(&self) -> Vec<Vec3> {
        let plan = &self.plan;
        let (pixels, spp) = (self.region.pixels(), plan.spp as usize);
        let mut out = vec![Vec3::ZERO; plan.samples(self.region)];
        for (pass, recs) in plan.passes.iter().zip(&self.recs) {
            let n = pass.n as usize;
            let call = &mut out[pass.call * pixels * spp..(pass.call + 1) * pixels * spp];
            for (px, recs) in call.chunks_exact_mut(spp).zip(recs.chunks_exact(n)) {
                for (v, rec) in px[pass.s0 as usize..].iter_mut().zip(recs) {
                    *v = rec.value;
                }
            }
        }
        out
    }
}
