//! A unit's pixels while its tiles come in: sums copied into place, or samples splatted as
//! they arrive ([`UnitSplat`]), and the buffers of ended units kept for the next ones.

use std::sync::mpsc::{self, Receiver, TryRecvError};

use crate::film::{Film, PixelStats};
use crate::pass::{PassSpec, TilePixels};
use crate::render::{Region, RenderSettings, DEFAULT_TILE};
use crate::splat::{SplatPlan, UnitFilm, UnitSplat};

use super::Splatting;

/// A unit's pixels while its tiles come in.
#[derive(Clone, Debug)]
pub(super) enum UnitPixels {
    /// Pixel sums: each tile's are copied into place.
    Sums(Film),
    /// Samples: each tile's pixels out of its neighbours' reach are splatted as it arrives,
    /// the rest when the unit ends.
    Samples(Box<UnitSplat>),
}

/// Buffers of ended units, for the next ones (a unit's film and samples are tens of
/// megabytes: allocated anew for every unit, their pages were faulted in again every time,
/// a fifth of the farm coordinator's page faults).
#[derive(Default)]
pub(super) struct Spares {
    films: Vec<Film>,
    /// (Two units are in flight at a time; boxed as `UnitPixels` holds them.)
    #[allow(clippy::vec_box)]
    splats: Vec<Box<UnitSplat>>,
    /// A film having its pages faulted in on the rayon pool ([`Spares::warm_up`]).
    warming: Option<Receiver<Film>>,
}

impl Spares {
    /// A film of `w x h` pixels to be overwritten: a kept one holds an earlier unit's
    /// pixels, which is fine for a unit's pixels (a unit of sums copies its tiles over every
    /// pixel; a splat overwrites every pixel it does not hold apart, [`UnitSplat::reuse`]).
    fn film(&mut self, (w, h): (u32, u32)) -> Film {
        if let Some(f) = self.films.pop() {
            if (f.width, f.height) == (w, h) {
                return f;
            }
        }
        match self.warming.as_ref().map(Receiver::try_recv) {
            Some(Err(TryRecvError::Empty)) | None => Film::new(w, h),
            Some(warmed) => {
                self.warming = None;
                let fits = |f: &Film| (f.width, f.height) == (w, h);
                warmed.ok().filter(fits).unwrap_or_else(|| Film::new(w, h))
            }
        }
    }

    /// Has a `w x h` film made, its pages faulted in, on the rayon pool, for the spares
    /// (unless one is on its way). Every iteration keeps its first unit's film, so the
    /// units' films need one new film an iteration: faulted in where a unit first writes
    /// it, that was 190 MB at 1920x1080 under a farm coordinator's lock (slow page faults
    /// on virtual machines: 0.2 s and more). The film's pixels are zeros either way.
    pub(super) fn warm_up(&mut self, (w, h): (u32, u32)) {
        if self.warming.is_some() {
            return;
        }
        let (tx, rx) = mpsc::sync_channel(1);
        rayon::spawn(move || {
            let mut film = Film::new(w, h);
            // one write a page faults every page in (a pixel is under a tenth of a page)
            let step = (4096 / std::mem::size_of::<PixelStats>()).max(1);
            film.pixels
                .iter_mut()
                .step_by(step)
                .for_each(|p| *p = PixelStats::default());
            let _ = tx.send(film);
        });
        self.warming = Some(rx);
    }

    /// Keeps an ended unit's film for a later unit (two at most).
    pub(super) fn keep(&mut self, film: UnitFilm) {
        if self.films.len() < 2 {
            self.films.push(film.into_buffer());
        }
    }
}

impl UnitPixels {
    /// The empty pixels of a unit of `spec` over a `size` image: sums, or a splat of its
    /// samples (with the session's `splatting`), from `spares` where it has them.
    pub(super) fn new(
        spec: &PassSpec,
        size: (u32, u32),
        splatting: &Splatting,
        spares: &mut Spares,
    ) -> Self {
        if !spec.sample_form() {
            return UnitPixels::Sums(spares.film(size));
        }
        let (calls, spp) = spec.render_calls();
        // the settings crate::pass::render_unit renders with (the pass sizes matter)
        let settings = RenderSettings {
            tile_size: DEFAULT_TILE,
            ..RenderSettings::new(Some(spp), None, splatting.seed)
        };
        let firsts: Vec<u64> = (0..calls as u64)
            .map(|c| spec.first_sample + c * spp as u64)
            .collect();
        let splat = match spares.splats.pop() {
            Some(mut s) => {
                s.reuse((&settings, spp), &firsts, spares.film(size));
                s
            }
            None => Box::new(UnitSplat::new(
                splatting.filter,
                size,
                (&settings, spp),
                &firsts,
            )),
        };
        UnitPixels::Samples(splat)
    }

    /// Puts a tile's pixels (checked to fit, [`TilePixels::fits`]) in place.
    pub(super) fn put(&mut self, tile: &TilePixels, region: Region, w: u32) {
        match (self, tile) {
            (UnitPixels::Sums(dst), TilePixels::Sums(src)) => {
                let (rw, w) = (region.width() as usize, w as usize);
                for (row, line) in src.pixels.chunks_exact(rw).enumerate() {
                    let start = (region.y0 as usize + row) * w + region.x0 as usize;
                    dst.pixels[start..start + rw].copy_from_slice(line);
                }
            }
            (UnitPixels::Samples(dst), TilePixels::Samples(src)) => dst.add(region, src),
            (UnitPixels::Samples(dst), TilePixels::Prepared(src)) => dst.add_prepared(src),
            _ => unreachable!("checked by check_tile"),
        }
    }

    /// Merges the interiors of the tiles in so far into `dst` ([`UnitSplat::merge_interiors`]:
    /// only for the oldest unit, whose film `dst` takes next).
    pub(super) fn merge_interiors(&mut self, dst: &mut Film) {
        if let UnitPixels::Samples(splat) = self {
            splat.merge_interiors(dst);
        }
    }

    /// How the unit's samples are splatted (`None` for a unit of sums).
    pub(super) fn plan(&self) -> Option<&SplatPlan> {
        match self {
            UnitPixels::Sums(_) => None,
            UnitPixels::Samples(splat) => Some(splat.plan()),
        }
    }

    /// Whether `tile`, which fits the unit's pass ([`TilePixels::fits`]), was prepared by
    /// this unit's plan if it was prepared at all.
    pub(super) fn accepts(&self, tile: &TilePixels) -> bool {
        match tile {
            TilePixels::Prepared(r) => self.plan() == Some(r.plan()),
            _ => true,
        }
    }

    /// The unit's film, once every one of its `tiles` is in.
    pub(super) fn film(self, tiles: &[Region], spares: &mut Spares) -> UnitFilm {
        match self {
            UnitPixels::Sums(film) => UnitFilm::whole(film),
            UnitPixels::Samples(mut splat) => {
                let film = splat.finish(tiles);
                if spares.splats.len() < 2 {
                    spares.splats.push(splat);
                }
                film
            }
        }
    }
}
