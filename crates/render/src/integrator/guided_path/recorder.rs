//! The path recorder: forward-loop suffix-radiance bookkeeping of a path's vertices for the
//! guide (doc section 2).

use super::*;

/// At most this many vertices of a path are recorded (doc section 2).
pub const MAX_RECORDED_VERTICES: usize = 32;

/// One recorded path vertex (doc section 2).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RecVertex {
    /// The vertex's position, in world space.
    pub position: Vec3,
    /// The guide's spatial leaf at `position` (from the vertex's [`VertexGuide`]).
    pub at: SLookup,
    /// The sampled direction leaving the vertex, in world space (unit).
    pub direction: Vec3,
    /// Throughput including this bounce's `f cos / p_mix` (before Russian roulette).
    pub throughput: Vec3,
    /// `f cos` of the sampled direction (BSDF value times the cosine; not divided by any pdf).
    pub fcos: Vec3,
    /// Mixture pdf (solid angle) the direction was sampled with.
    pub p_mix: f32,
    /// The BSDF's solid-angle pdf of the direction.
    pub p_bsdf: f32,
    /// The guide's solid-angle pdf of the direction.
    pub p_guide: f32,
    /// Statistical weight (1, or 0.5 while NEE kick-start is active).
    pub weight: f32,
    /// Radiance accumulator R_i: the contributions added to the pixel since the vertex.
    pub acc: Vec3,
}

impl RecVertex {
    /// `L_i = R_i / T_i` per channel where `T_i p_mix > 1e-4`, else 0.
    pub fn incident_radiance(&self) -> Vec3 {
        let f = |r: f32, t: f32| if t * self.p_mix > 1e-4 { r / t } else { 0.0 };
        Vec3::new(
            f(self.acc.x, self.throughput.x),
            f(self.acc.y, self.throughput.y),
            f(self.acc.z, self.throughput.z),
        )
    }

    /// The guide record of this vertex (`learn_fraction`: fill the fraction-gradient fields).
    pub fn record(&self, learn_fraction: bool) -> Record {
        let l = self.incident_radiance();
        let mean = |v: Vec3| (v.x + v.y + v.z) / 3.0;
        Record {
            position: self.position,
            direction: self.direction,
            radiance: mean(l),
            pdf_mix: self.p_mix,
            weight: self.weight,
            product: if learn_fraction {
                mean(l * self.fcos)
            } else {
                0.0
            },
            pdf_bsdf: self.p_bsdf,
            pdf_guide: self.p_guide,
            is_delta: false,
        }
    }
}

/// Forward-loop suffix-radiance bookkeeping for one path. Costs nothing until the first
/// [`PathRecorder::push`] (paths that are not recorded never touch it).
#[derive(Clone, Debug, Default)]
pub struct PathRecorder {
    /// The open vertices (at most [`MAX_RECORDED_VERTICES`]).
    v: Vec<RecVertex>,
    /// The last pushed vertex is the path vertex whose sampled direction the next hit
    /// lies along.
    last_is_previous: bool,
}

impl PathRecorder {
    /// The open vertices.
    pub fn vertices(&self) -> &[RecVertex] {
        &self.v
    }

    /// Opens a vertex for the direction just sampled (false when full).
    pub fn push(&mut self, v: RecVertex) -> bool {
        if self.v.len() >= MAX_RECORDED_VERTICES {
            self.last_is_previous = false;
            return false;
        }
        if self.v.capacity() == 0 {
            self.v.reserve_exact(MAX_RECORDED_VERTICES);
        }
        self.v.push(RecVertex {
            acc: Vec3::ZERO,
            ..v
        });
        self.last_is_previous = true;
        true
    }

    /// The path went on from a vertex that was not recorded (delta lobe, full buffer).
    pub fn skip(&mut self) {
        self.last_is_previous = false;
    }

    /// A contribution `c` added to the pixel (NEE, or emission with `indirect_only` false).
    #[inline]
    pub fn add(&mut self, c: Vec3) {
        for v in &mut self.v {
            v.acc += c;
        }
    }

    /// Emission `c` found by the direction sampled at the previous vertex. With
    /// `indirect_only` (NEE always) it is withheld from that vertex when that vertex did NEE
    /// (`prev_nee`): it learns indirect light only.
    #[inline]
    pub fn add_emission(&mut self, c: Vec3, indirect_only: bool, prev_nee: bool) {
        let end = if indirect_only && prev_nee && self.last_is_previous {
            self.v.len() - 1
        } else {
            self.v.len()
        };
        for v in &mut self.v[..end] {
            v.acc += c;
        }
    }

    /// Deposits every vertex into the tree's building statistics.
    pub fn commit(&self, tree: &SdTree, learn_fraction: bool, rng: &mut Rng) {
        for v in self.vertices() {
            tree.record_at(&v.record(learn_fraction), &v.at, &mut || rng.next_f32());
        }
    }
}
