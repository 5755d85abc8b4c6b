//! A unit's film as [`crate::UnitSplat::finish`] hands it over: the whole image's film, less
//! the interiors of the tiles prepared apart, which stay in their own films. Merging it into
//! an iteration's film reads each pixel from where it is held, so the interiors are never
//! copied into the unit's film (a 1920x1080 unit's are 190 MB, copied under a farm
//! coordinator's lock at every upload).

use std::sync::Arc;

use rayon::prelude::*;

use crate::film::{Film, PixelStats};
use crate::render::Region;

/// A unit's pixels: `film` holds every pixel but those of `interiors` and `merged`, whose
/// pixels there are stale (an earlier unit's) and never read.
#[derive(Debug)]
pub struct UnitFilm {
    pub(crate) film: Film,
    /// Disjoint regions and their pixels (a region-sized film each).
    pub(crate) interiors: Vec<(Region, Arc<Film>)>,
    /// Regions whose pixels were merged already ([`crate::UnitSplat::merge_interiors`]):
    /// skipped by [`UnitFilm::merge_into`].
    pub(crate) merged: Vec<Region>,
}

impl UnitFilm {
    /// A unit film whose every pixel is in `film`.
    pub fn whole(film: Film) -> Self {
        UnitFilm {
            film,
            interiors: Vec::new(),
            merged: Vec::new(),
        }
    }

    /// Adds every pixel's sums to `dst`'s (of the same size), pixel by pixel: the same bits
    /// as merging the film with its interiors in place ([`Film::merge`]), however the rows
    /// are shared among threads. The `merged` regions are left as they are.
    pub fn merge_into(&self, dst: &mut Film) {
        let (w, h) = (self.film.width, self.film.height);
        assert_eq!((dst.width, dst.height), (w, h));
        let held = self.interiors.iter().map(|(r, f)| (*r, Some(f)));
        let mut order: Vec<(Region, Option<&Arc<Film>>)> =
            held.chain(self.merged.iter().map(|r| (*r, None))).collect();
        order.sort_by_key(|(r, _)| r.x0);
        let w = w as usize;
        (dst.pixels.par_chunks_mut(w).enumerate()).for_each(|(y, line)| {
            let src = &self.film.pixels[y * w..(y + 1) * w];
            let mut x = 0;
            let y = y as u32;
            for (r, f) in order.iter().filter(|(r, _)| r.y0 <= y && y < r.y1) {
                let (x0, x1, rw) = (r.x0 as usize, r.x1 as usize, r.width() as usize);
                merge_run(&mut line[x..x0], &src[x..x0]);
                if let Some(f) = f {
                    let row = (y - r.y0) as usize * rw;
                    merge_run(&mut line[x0..x1], &f.pixels[row..row + rw]);
                }
                x = x1;
            }
            merge_run(&mut line[x..], &src[x..]);
        });
    }

    /// The unit's pixels as one film (the interiors copied into place). Not for a unit some
    /// of whose pixels were merged already (it panics).
    pub fn into_film(self) -> Film {
        assert!(self.merged.is_empty(), "a unit film partly merged already");
        let mut film = self.film;
        for (r, f) in &self.interiors {
            each_row(&mut film, *r, f, <[PixelStats]>::copy_from_slice);
        }
        film
    }

    /// The whole-image film (its interiors' pixels stale), for reuse by a later unit.
    pub fn into_buffer(self) -> Film {
        self.film
    }
}

/// Merges a region's pixels `f` (a region-sized film) into the same pixels of the
/// whole-image `dst`, pixel by pixel as [`UnitFilm::merge_into`] does.
pub(crate) fn merge_region(dst: &mut Film, r: Region, f: &Film) {
    each_row(dst, r, f, merge_run);
}

/// `op(row of r in dst, the same row of f)` for every row of region `r`, `f` its pixels.
fn each_row(dst: &mut Film, r: Region, f: &Film, op: impl Fn(&mut [PixelStats], &[PixelStats])) {
    let (w, rw) = (dst.width as usize, r.width() as usize);
    for (row, line) in f.pixels.chunks_exact(rw).enumerate() {
        let start = (r.y0 as usize + row) * w + r.x0 as usize;
        op(&mut dst.pixels[start..start + rw], line);
    }
}

fn merge_run(dst: &mut [PixelStats], src: &[PixelStats]) {
    for (p, q) in dst.iter_mut().zip(src) {
        p.merge(q);
    }
}
