//! How the coordinator cuts a unit into tiles. Any tiling gives the same bits (a pixel's
//! additions do not depend on its tile), so the tiling is free to serve speed alone:
//!
//! * **Big tiles first, small ones last.** A tile re-renders its filter halo and costs a
//!   lease round trip and a statistics upload, so tiles should be big; a unit ends when its
//!   last tile is in, so the last tiles should be small (guided self-scheduling: each tile
//!   takes a share of the work still left, [`shares`]). [`CostMap`] remembers what each part
//!   of the image cost per sample in the job's earlier units (measured by the workers), and
//!   [`CostMap::tiles`] bisects the image recursively where the cost divides as the tiles'
//!   shares do, handing out the most costly first.
//! * **Not too small, not too few.** No tile is planned below [`MIN_TILE_SECONDS`] of work
//!   or 1/([`TAIL_TILES`] x worker threads) of the unit, but the smallest share is at most
//!   1/([`TILES_PER_SLOT`] x worker threads), so a short unit still has a few tiles per
//!   thread; before anything is measured, a unit is cut into [`TILES_PER_SLOT`] equal tiles
//!   per worker thread.
//!
//! A job that sets a tile size gets plain square tiles of that size instead
//! ([`pathfarm_render::Region::tiles`]).

use pathfarm_render::Region;

/// Tiles per worker thread of a unit cut before any cost was measured.
pub const TILES_PER_SLOT: usize = 3;

/// The smallest tile is 1/(this x worker threads) of the unit's work: what a worker may wait
/// for at the unit's end.
pub const TAIL_TILES: usize = 24;

/// No tile is planned below this much work (seconds on one thread): lease, upload and the
/// statistics of a tile cost tens of milliseconds.
pub const MIN_TILE_SECONDS: f64 = 0.05;

/// Edge of the cells a [`CostMap`] keeps one cost density for, in pixels.
pub const CELL: u32 = 16;

/// No tile side is cut below this many pixels (unless the image is smaller).
pub const MIN_SIDE: u32 = 16;

/// Seconds per sample of each [`CELL`]-sized cell of the image, as measured in the job's
/// previous units (uniform until a unit has been measured).
#[derive(Clone, Debug)]
pub struct CostMap {
    width: u32,
    height: u32,
    cols: usize,
    rows: usize,
    density: Vec<f64>,
    /// Whether any unit has been measured (else `density` is a uniform placeholder).
    measured: bool,
}

impl CostMap {
    /// A uniform map of a `width x height` image.
    pub fn new(width: u32, height: u32) -> Self {
        let cols = width.div_ceil(CELL).max(1) as usize;
        let rows = height.div_ceil(CELL).max(1) as usize;
        Self {
            width,
            height,
            cols,
            rows,
            density: vec![1.0; cols * rows],
            measured: false,
        }
    }

    /// Records that `region` cost `seconds_per_sample` per sample of its pixels: the cells it
    /// covers take that density (a cell's last measurement wins).
    pub fn record(&mut self, region: Region, seconds_per_sample: f64) {
        if !(seconds_per_sample.is_finite() && seconds_per_sample > 0.0) {
            return;
        }
        if !self.measured {
            // the placeholder is not seconds: start from this measurement everywhere
            self.density.fill(seconds_per_sample);
            self.measured = true;
        }
        let (cx0, cy0) = ((region.x0 / CELL) as usize, (region.y0 / CELL) as usize);
        let cx1 = (region.x1.div_ceil(CELL) as usize).min(self.cols);
        let cy1 = (region.y1.div_ceil(CELL) as usize).min(self.rows);
        for cy in cy0..cy1 {
            for cx in cx0..cx1 {
                self.density[cy * self.cols + cx] = seconds_per_sample;
            }
        }
    }

    /// The image cut into tiles for a unit of `spp` samples per pixel shared among `slots`
    /// worker threads: shares of the estimated work from [`shares`] (or [`TILES_PER_SLOT`]
    /// equal tiles per slot before anything was measured), most costly first. Tiles are at
    /// least [`MIN_SIDE`] pixels a side (fewer tiles if the image is too small for that).
    pub fn tiles(&self, slots: usize, spp: u64) -> Vec<Region> {
        let slots = slots.max(1);
        let weights = if self.measured {
            let seconds = self.cost(Region::full(self.width, self.height)) * spp.max(1) as f64;
            let min_share = (1.0 / (TAIL_TILES * slots) as f64)
                .max(MIN_TILE_SECONDS / seconds.max(1e-9))
                .min(1.0 / (TILES_PER_SLOT * slots) as f64);
            shares(slots, min_share)
        } else {
            vec![1.0; TILES_PER_SLOT * slots]
        };
        self.tiles_weighted(&weights)
    }

    /// The image cut into tiles whose costs are proportional to `weights` (as nearly as whole
    /// pixels and [`MIN_SIDE`] allow), most costly first.
    pub fn tiles_weighted(&self, weights: &[f64]) -> Vec<Region> {
        let mut out = Vec::with_capacity(weights.len().max(1));
        let w: Vec<f64> = weights.iter().map(|x| x.max(1e-12)).collect();
        self.bisect(Region::full(self.width, self.height), &w, &mut out);
        let mut costed: Vec<(f64, Region)> = out.into_iter().map(|r| (self.cost(r), r)).collect();
        // Most costly first; ties in image order, so the tiling is a function of the map.
        costed.sort_by(|a, b| {
            b.0.total_cmp(&a.0)
                .then((a.1.y0, a.1.x0).cmp(&(b.1.y0, b.1.x0)))
        });
        costed.into_iter().map(|(_, r)| r).collect()
    }

    /// Cuts `r` into tiles of costs proportional to `weights` (at least one): the weights are
    /// split in two runs of about equal sum, and `r` along its longer side where its cost
    /// divides as the two runs do.
    fn bisect(&self, r: Region, weights: &[f64], out: &mut Vec<Region>) {
        let along_x = r.width() >= r.height();
        let side = if along_x { r.width() } else { r.height() };
        if weights.len() <= 1 || side < 2 * MIN_SIDE {
            out.push(r);
            return;
        }
        let total_w: f64 = weights.iter().sum();
        let mut split = 1;
        let mut best = f64::INFINITY;
        let mut acc = 0.0;
        for (i, w) in weights.iter().enumerate().take(weights.len() - 1) {
            acc += w;
            let d = (acc - 0.5 * total_w).abs();
            if d < best {
                best = d;
                split = i + 1;
            }
        }
        let left = &weights[..split];
        let share = left.iter().sum::<f64>() / total_w;
        let profile = self.profile(r, along_x);
        let total: f64 = profile.iter().sum();
        let mut acc = 0.0;
        let mut cut = profile.len();
        for (i, c) in profile.iter().enumerate() {
            acc += c;
            if acc >= share * total {
                cut = i + 1;
                break;
            }
        }
        let cut = (cut as u32).clamp(MIN_SIDE, side - MIN_SIDE);
        let (a, b) = if along_x {
            let m = r.x0 + cut;
            (Region { x1: m, ..r }, Region { x0: m, ..r })
        } else {
            let m = r.y0 + cut;
            (Region { y1: m, ..r }, Region { y0: m, ..r })
        };
        self.bisect(a, left, out);
        self.bisect(b, &weights[split..], out);
    }

    /// The cost of each pixel column (`along_x`) or row of `r`.
    fn profile(&self, r: Region, along_x: bool) -> Vec<f64> {
        let (lo, hi) = if along_x { (r.x0, r.x1) } else { (r.y0, r.y1) };
        (lo..hi)
            .map(|i| {
                let line = if along_x {
                    Region {
                        x0: i,
                        x1: i + 1,
                        ..r
                    }
                } else {
                    Region {
                        y0: i,
                        y1: i + 1,
                        ..r
                    }
                };
                self.cost(line)
            })
            .collect()
    }

    /// The estimated cost of `r`: each cell's density times the pixels of `r` in it.
    pub fn cost(&self, r: Region) -> f64 {
        let mut total = 0.0;
        let (cy0, cy1) = (r.y0 / CELL, r.y1.div_ceil(CELL));
        let (cx0, cx1) = (r.x0 / CELL, r.x1.div_ceil(CELL));
        for cy in cy0..cy1.min(self.rows as u32) {
            let h = r.y1.min((cy + 1) * CELL) - r.y0.max(cy * CELL);
            for cx in cx0..cx1.min(self.cols as u32) {
                let w = r.x1.min((cx + 1) * CELL) - r.x0.max(cx * CELL);
                total += self.density[cy as usize * self.cols + cx as usize] * (w * h) as f64;
            }
        }
        total
    }
}

/// Guided self-scheduling shares of a unit's work among `slots` worker threads: each tile
/// takes 1/(2 slots) of the work still left, but not less than `min_share`; the last takes the
/// rest. Sums to 1, non-increasing (but for the last).
pub fn shares(slots: usize, min_share: f64) -> Vec<f64> {
    let min_share = min_share.clamp(1e-4, 1.0);
    let mut left = 1.0;
    let mut out = Vec::new();
    while left > 1.5 * min_share {
        let s = (left / (2 * slots.max(1)) as f64).max(min_share);
        out.push(s);
        left -= s;
    }
    match out.last_mut() {
        Some(last) => *last += left,
        None => out.push(1.0),
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn covers(tiles: &[Region], w: u32, h: u32) -> bool {
        let mut seen = vec![0u8; (w * h) as usize];
        for t in tiles {
            for y in t.y0..t.y1 {
                for x in t.x0..t.x1 {
                    seen[(y * w + x) as usize] += 1;
                }
            }
        }
        seen.iter().all(|&c| c == 1)
    }

    #[test]
    fn tiles_cover_the_image_exactly_once() {
        for (w, h) in [(640, 360), (40, 24), (17, 5), (1, 1), (1000, 16)] {
            let mut map = CostMap::new(w, h);
            for slots in [1, 2, 3, 7, 64] {
                let t = map.tiles(slots, 16);
                assert!(covers(&t, w, h), "{w}x{h} for {slots}: {t:?}");
                for r in &t {
                    let ok = r.width() >= MIN_SIDE.min(w) && r.height() >= MIN_SIDE.min(h);
                    assert!(ok, "{r:?} is a sliver");
                }
            }
            map.record(Region::full(w, h), 1e-5);
            for slots in [1, 2, 3, 7, 64] {
                let t = map.tiles(slots, 16);
                assert!(covers(&t, w, h), "{w}x{h} for {slots}: {t:?}");
            }
        }
        // before a measurement: TILES_PER_SLOT equal tiles per slot
        assert_eq!(CostMap::new(640, 360).tiles(2, 1).len(), 2 * TILES_PER_SLOT);
    }

    #[test]
    fn shares_shrink_to_the_minimum_and_sum_to_one() {
        for (slots, min) in [(1, 0.5), (2, 1.0 / 48.0), (8, 1.0 / 192.0), (3, 0.01)] {
            let s = shares(slots, min);
            assert!((s.iter().sum::<f64>() - 1.0).abs() < 1e-9, "{s:?}");
            let body = &s[..s.len() - 1];
            assert!(body.windows(2).all(|w| w[0] >= w[1]), "{s:?}");
            assert!(s.iter().all(|&x| x >= min * 0.999), "{s:?}");
            assert!(s[0] <= 1.0 / (2 * slots) as f64 + 1e-12 || s.len() == 1);
        }
        assert_eq!(shares(4, 1.0), vec![1.0]);
    }

    #[test]
    fn tiles_follow_a_measured_cost() {
        // The bottom half of the image cost 9x the top: costs follow the planned shares
        // (within 30 %: cuts are on whole pixels), and cheap pixels go into bigger tiles.
        let mut map = CostMap::new(640, 360);
        map.record(
            Region {
                x0: 0,
                y0: 0,
                x1: 640,
                y1: 176,
            },
            1e-6,
        );
        map.record(
            Region {
                x0: 0,
                y0: 176,
                x1: 640,
                y1: 360,
            },
            9e-6,
        );
        let weights = [1.0; 8];
        let tiles = map.tiles_weighted(&weights);
        assert_eq!(tiles.len(), 8);
        let costs: Vec<f64> = tiles.iter().map(|&t| map.cost(t)).collect();
        let mean = costs.iter().sum::<f64>() / costs.len() as f64;
        assert!(
            costs.iter().all(|&c| c < 1.3 * mean && c > 0.7 * mean),
            "{costs:?}"
        );
        assert!(
            costs.windows(2).all(|w| w[0] >= w[1]),
            "most costly first: {costs:?}"
        );
        let areas: Vec<usize> = tiles.iter().map(|t| t.pixels()).collect();
        let (lo, hi) = (areas.iter().min().unwrap(), areas.iter().max().unwrap());
        assert!(
            *hi > 2 * lo,
            "cheap pixels go into bigger tiles ({areas:?})"
        );
        // a long unit on 2 threads: big tiles first, the last ones small
        let tiles = map.tiles(2, 1_000_000);
        let costs: Vec<f64> = tiles.iter().map(|&t| map.cost(t)).collect();
        let total: f64 = costs.iter().sum();
        assert!(costs[0] > 0.15 * total, "{costs:?}");
        let smallest = costs.iter().cloned().fold(f64::INFINITY, f64::min);
        assert!(smallest < 0.04 * total, "{costs:?}");
    }

    #[test]
    fn non_finite_or_zero_measurements_are_ignored() {
        let mut map = CostMap::new(64, 64);
        let before = map.cost(Region::full(64, 64));
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            map.record(Region::full(64, 64), bad);
        }
        assert_eq!(map.cost(Region::full(64, 64)), before);
    }
}
