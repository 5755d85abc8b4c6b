//! Restricting a directional quadtree to part of the sphere (e.g. the hemisphere a surface
//! reflects into).
//!
//! A quadtree learns incident radiance over the whole sphere, but at an opaque surface only the
//! hemisphere on the viewer's side can contribute: a guide sample below the surface is a wasted
//! sample (about 15 % of guide samples on veach-ajar and the Cornell box, where a spatial leaf
//! holds surfaces of several orientations, or both sides of a thin door). The remedy here
//! samples the quadtree's density restricted to a [`CellMask`], a set of cells of the 4x4 grid of
//! depth-2 quadrants of the `(u, v)` square, renormalised by the mass of those cells
//! ([`Restriction`]). In the cylindrical mapping the hemisphere of an axis-aligned normal is
//! exactly 8 of these cells (`z` splits `u` at 0.5, `x` and `y` split `v` at quarters), which
//! is what architectural scenes are made of; for other normals the mask keeps every cell that
//! reaches above the surface, so less is gained but nothing is lost.
//!
//! The cells can also carry weights ([`CellWeights`]): [`CellWeights::cosine`] approximates the
//! clamped cosine of a surface per cell, so that the guide samples incident radiance x cosine,
//! the product a diffuse surface integrates, instead of incident radiance alone (a coarse
//! product: the weight is constant over a cell; within it the quadtree decides).
//!
//! Any mask and any positive weights are unbiased as long as sampling and pdf use the same
//! ones, and the BSDF side of the mixture still covers every direction the guide leaves out.

use glam::{Vec2, Vec3};

#[cfg(test)]
mod tests;

/// Cells of the 4x4 grid over `(u, v)`, bit `iu + 4 iv` for the cell
/// `[iu/4, (iu+1)/4) x [iv/4, (iv+1)/4)`. In directions: `iu` is a band of `z = cos(theta)`
/// (`[-1, -0.5)`, `[-0.5, 0)`, `[0, 0.5)`, `[0.5, 1]`), `iv` a quarter of `phi`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct CellMask(pub u16);

/// A cell is kept by [`CellMask::hemisphere`] when some direction in it has `n . w` above this
/// (directions closer to the horizon carry at most this fraction of a cosine-weighted lobe;
/// it also keeps a normal a rounding error away from an axis from keeping slivers).
pub const HEMISPHERE_EPSILON: f32 = 1e-3;

impl CellMask {
    /// Every cell: no restriction.
    pub const ALL: Self = Self(0xffff);

    /// The cell of `uv` (clamped to the square), as a bit index `iu + 4 iv`.
    #[inline]
    pub fn cell_of(uv: Vec2) -> u32 {
        // Exact: multiplying by 4 only shifts the exponent.
        let iu = ((uv.x.clamp(0.0, 1.0) * 4.0) as u32).min(3);
        let iv = ((uv.y.clamp(0.0, 1.0) * 4.0) as u32).min(3);
        iu + 4 * iv
    }

    /// The cell of the direction `d` without the azimuth's arctangent: the band from `d.z` as
    /// [`crate::dir_to_uv`] computes `u`, the quarter of phi from the signs of `d.x` and `d.y`.
    /// Equal to `cell_of(dir_to_uv(d))` except within rounding of a quarter's edge (where the
    /// mapping's arctangent may land on the other side): for estimates, not for pdfs.
    #[inline]
    pub fn cell_of_dir(d: Vec3) -> u32 {
        let u = ((d.z.clamp(-1.0, 1.0) + 1.0) * 0.5).clamp(0.0, 1.0);
        let iu = ((u * 4.0) as u32).min(3);
        let iv = match (d.x >= 0.0, d.y >= 0.0) {
            (true, true) => 0,
            (false, true) => 1,
            (false, false) => 2,
            (true, false) => 3,
        };
        iu + 4 * iv
    }

    /// Whether the cell of `uv` is in the mask.
    #[inline]
    pub fn contains_uv(self, uv: Vec2) -> bool {
        self.0 & (1 << Self::cell_of(uv)) != 0
    }

    /// The cells holding some direction `w` of the open hemisphere around the unit normal `n`
    /// with `n . w >` [`HEMISPHERE_EPSILON`]: for each cell, the exact maximum of `n . w` over
    /// it. All cells for a non-finite or zero `n`.
    pub fn hemisphere(n: Vec3) -> Self {
        if !n.is_finite() || n == Vec3::ZERO {
            return Self::ALL;
        }
        let max = cell_max_cosines(n);
        let mut mask = 0u16;
        for (i, m) in max.iter().enumerate() {
            if *m > HEMISPHERE_EPSILON {
                mask |= 1 << i;
            }
        }
        Self(mask)
    }
}

/// The exact maximum of `n . w` over each cell of the 4x4 grid (index `iu + 4 iv`).
///
/// Over a cell, n . w = nz z + sqrt(1 - z^2) (nx cos phi + ny sin phi). For a quarter k of
/// phi, [k pi/2, (k+1) pi/2], the largest value of the bracket is |n_xy| when n's azimuth
/// lies in the quarter, else the larger of its values at the two edges, which are e_k and
/// e_{k+1} with e = (nx, ny, -nx, -ny). Then g(z) = nz z + c sqrt(1 - z^2) is concave for
/// c > 0 (maximum at z* = nz / sqrt(nz^2 + c^2), value sqrt(nz^2 + c^2)), else largest at an
/// end of the band.
///
/// The per-quarter values are computed once (4 lanes) and the per-cell ones over all 16 cells
/// at once from constant tables, so that it compiles to vector code (it runs at every guided
/// vertex); the arithmetic is the scalar loop's, operation for operation (a test compares
/// the bits).
#[inline]
pub(crate) fn cell_max_cosines(n: Vec3) -> [f32; 16] {
    let e = [n.x, n.y, -n.x, -n.y];
    let r = (n.x * n.x + n.y * n.y).sqrt();
    let mut c4 = [0.0f32; 4];
    let mut peak4 = [0.0f32; 4];
    let mut zs4 = [0.0f32; 4];
    for k in 0..4 {
        let (a, b) = (e[k], e[(k + 1) % 4]);
        let c = if a >= 0.0 && b >= 0.0 { r } else { a.max(b) };
        let peak = (n.z * n.z + c * c).sqrt();
        c4[k] = c;
        peak4[k] = peak;
        zs4[k] = if c > 0.0 { n.z / peak } else { f32::NAN };
    }
    let mut out = [0.0f32; 16];
    for i in 0..16 {
        let k = i >> 2;
        let (c, peak, zs) = (c4[k], peak4[k], zs4[k]);
        let m = (n.z * BAND_Z0[i] + c * BAND_S0[i]).max(n.z * BAND_Z1[i] + c * BAND_S1[i]);
        out[i] = if zs >= BAND_Z0[i] && zs <= BAND_Z1[i] {
            m.max(peak)
        } else {
            m
        };
    }
    out
}

/// Per cell `iu + 4 iv`: the lower and upper `z` of its band and `sqrt(1 - z^2)` there.
const BAND_Z0: [f32; 16] = band_table([-1.0, -0.5, 0.0, 0.5]);
const BAND_Z1: [f32; 16] = band_table([-0.5, 0.0, 0.5, 1.0]);
const BAND_S0: [f32; 16] = band_table([0.0, 0.866_025_4, 1.0, 0.866_025_4]);
const BAND_S1: [f32; 16] = band_table([0.866_025_4, 1.0, 0.866_025_4, 0.0]);

const fn band_table(per_band: [f32; 4]) -> [f32; 16] {
    let mut t = [0.0; 16];
    let mut i = 0;
    while i < 16 {
        t[i] = per_band[i & 3];
        i += 1;
    }
    t
}

/// The scalar form of [`cell_max_cosines`], which the tests compare it with bit for bit.
#[cfg(test)]
pub(crate) fn cell_max_cosines_scalar(n: Vec3) -> [f32; 16] {
    let e = [n.x, n.y, -n.x, -n.y];
    let r = (n.x * n.x + n.y * n.y).sqrt();
    const Z: [f32; 5] = [-1.0, -0.5, 0.0, 0.5, 1.0];
    const S: [f32; 5] = [0.0, 0.866_025_4, 1.0, 0.866_025_4, 0.0];
    let mut out = [0.0f32; 16];
    for k in 0..4 {
        let (a, b) = (e[k], e[(k + 1) % 4]);
        let c = if a >= 0.0 && b >= 0.0 { r } else { a.max(b) };
        let peak = (n.z * n.z + c * c).sqrt();
        let z_star = if c > 0.0 { n.z / peak } else { f32::NAN };
        for iu in 0..4 {
            let (z0, z1) = (Z[iu], Z[iu + 1]);
            let mut m = (n.z * z0 + c * S[iu]).max(n.z * z1 + c * S[iu + 1]);
            if z_star >= z0 && z_star <= z1 {
                m = m.max(peak);
            }
            out[iu + 4 * k] = m;
        }
    }
    out
}

/// The scalar form of [`CellWeights::cosine`] over [`cell_max_cosines_scalar`], which the
/// tests compare it with bit for bit.
#[cfg(test)]
pub(crate) fn cosine_weights_scalar(n: Vec3) -> CellWeights {
    if !n.is_finite() || n == Vec3::ZERO {
        return CellWeights::ALL;
    }
    let max = cell_max_cosines_scalar(n);
    let [dx, dy, dz] = &*MEAN_DIRS;
    let mut weight = [1.0f32; 16];
    let mut mask = 0u16;
    for i in 0..16 {
        if max[i] > HEMISPHERE_EPSILON {
            mask |= 1 << i;
            weight[i] = n.dot(Vec3::new(dx[i], dy[i], dz[i])).max(0.25 * max[i]);
        }
    }
    CellWeights {
        mask: CellMask(mask),
        weight,
    }
}

/// Mean of `w` over each cell (index `iu + 4 iv`) as `(x, y, z)` coefficients: the mean of
/// `n . w` over the cell is `n . d` with `d = (x[cell], y[cell], z[cell])` (exact: the
/// integral is linear in `n`).
/// Over a cell `[z0, z1] x [p0, p1]` (area `(z1 - z0)(p1 - p0)` = pi / 4), the integral of
/// `w_x` is `(F(z1) - F(z0)) (sin p1 - sin p0)` with `F(z) = (z sqrt(1 - z^2) + asin z) / 2`,
/// of `w_y` `(F(z1) - F(z0)) (cos p0 - cos p1)`, of `w_z` `(z1^2 - z0^2) / 2 (p1 - p0)`.
/// By component (`[x; 16], [y; 16], [z; 16]`), for vector code.
fn cell_mean_dirs() -> [[f32; 16]; 3] {
    let f = |z: f64| (z * (1.0 - z * z).max(0.0).sqrt() + z.asin()) * 0.5;
    let mut out = [[0.0f32; 16]; 3];
    for iv in 0..4 {
        let (p0, p1) = (
            iv as f64 * std::f64::consts::FRAC_PI_2,
            (iv + 1) as f64 * std::f64::consts::FRAC_PI_2,
        );
        for iu in 0..4 {
            let (z0, z1) = (iu as f64 * 0.5 - 1.0, (iu + 1) as f64 * 0.5 - 1.0);
            let area = (z1 - z0) * (p1 - p0);
            let fz = f(z1) - f(z0);
            let cell = iu + 4 * iv;
            out[0][cell] = (fz * (p1.sin() - p0.sin()) / area) as f32;
            out[1][cell] = (fz * (p0.cos() - p1.cos()) / area) as f32;
            out[2][cell] = ((z1 * z1 - z0 * z0) * 0.5 * (p1 - p0) / area) as f32;
        }
    }
    out
}

static MEAN_DIRS: std::sync::LazyLock<[[f32; 16]; 3]> = std::sync::LazyLock::new(cell_mean_dirs);

/// A [`CellMask`] with a weight per cell: the part of the sphere a guide samples from, each
/// cell's density scaled by its weight before renormalising (see [`Restriction`]). Weights
/// outside the mask are unused and kept at 1.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellWeights {
    /// The cells sampled from.
    pub mask: CellMask,
    /// Factor of each cell's density, positive in the mask (index `iu + 4 iv`).
    pub weight: [f32; 16],
}

impl CellWeights {
    /// Every cell, unweighted: no restriction.
    pub const ALL: Self = Self {
        mask: CellMask::ALL,
        weight: [1.0; 16],
    };

    /// The clamped cosine `max(0, n . w)` of the surface with unit normal `n`, approximated
    /// per cell: the cells of [`CellMask::hemisphere`], weighted by the cell's mean of `n . w`
    /// where that is at least a quarter of the cell's maximum, else by that quarter (cells
    /// straddling the horizon, whose mean counts the part below as negative). Exact means for
    /// cells wholly above the surface, e.g. 0.25 and 0.75 for the two bands of a horizontal
    /// floor. Guiding toward radiance x cosine is the product a diffuse surface integrates;
    /// any positive weights stay unbiased (the sampler and the pdf use the same ones).
    /// [`CellWeights::ALL`] for a non-finite or zero `n`.
    pub fn cosine(n: Vec3) -> Self {
        if !n.is_finite() || n == Vec3::ZERO {
            return Self::ALL;
        }
        let max = cell_max_cosines(n);
        let [dx, dy, dz] = &*MEAN_DIRS;
        let mut weight = [1.0f32; 16];
        let mut mask = 0u16;
        // (n . d as glam's Vec3::dot computes it: x, then + y, then + z)
        for i in 0..16 {
            let inside = max[i] > HEMISPHERE_EPSILON;
            let w = (n.x * dx[i] + n.y * dy[i] + n.z * dz[i]).max(0.25 * max[i]);
            weight[i] = if inside { w } else { 1.0 };
            mask |= (inside as u16) << i;
        }
        Self {
            mask: CellMask(mask),
            weight,
        }
    }
}

impl From<CellMask> for CellWeights {
    fn from(mask: CellMask) -> Self {
        Self {
            mask,
            weight: [1.0; 16],
        }
    }
}

/// A quadtree's density restricted to the cells of `mask` and weighted per cell: the density
/// is the tree's times the cell's `weight`, divided by `mass` (the weighted probability the
/// tree gives those cells), inside them and 0 outside. Made by
/// [`crate::SamplingDTree::restrict`], which falls back to no restriction (`ALL`, mass
/// exactly 1) when the mask holds no probability.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Restriction {
    /// The cells sampled from.
    pub mask: CellMask,
    /// The tree's probability of those cells, each times its weight (1 for `NONE`).
    pub mass: f32,
    /// Factor of each cell's density before renormalising (1 for a plain mask).
    pub weight: [f32; 16],
}

impl Restriction {
    /// No restriction.
    pub const NONE: Self = Self {
        mask: CellMask::ALL,
        mass: 1.0,
        weight: [1.0; 16],
    };
}

impl Default for Restriction {
    fn default() -> Self {
        Self::NONE
    }
}
