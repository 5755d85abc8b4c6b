//! Configuration of the SD-tree guide.

/// Spatial filter applied when recording (doc section 7).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum SpatialFilter {
    /// Record into the leaf containing the position (the 2017 paper).
    #[default]
    Nearest,
    /// Jitter the position uniformly within +-1/2 of the leaf's extent (caller-supplied
    /// random numbers), clamp to the domain, record into the leaf found there.
    Stochastic,
    /// Splat a box of the leaf's size centred on the position; every overlapped leaf gets the
    /// record with weight `w * overlap / box volume` (mass beyond the domain goes to the border
    /// leaves, exactly as clamping the stochastic filter's jitter would).
    Box,
}

/// Directional filter applied when recording.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum DirectionalFilter {
    /// Deposit into the building leaf cell containing the direction.
    #[default]
    Nearest,
    /// Splat a square of the building leaf cell's size centred on the direction, wrapping
    /// across the phi seam (mass is conserved exactly).
    Box,
}

/// Loss whose gradient trains the learned BSDF-sampling fraction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum FractionLoss {
    /// KL divergence (gradient exponent p = 1).
    #[default]
    Kl,
    /// Variance (gradient exponent p = 2).
    Var,
}

impl FractionLoss {
    /// The exponent `p` of `(F / q)^p` in the gradient.
    pub fn exponent(self) -> i32 {
        match self {
            FractionLoss::Kl => 1,
            FractionLoss::Var => 2,
        }
    }
}

/// How the probability alpha of sampling the BSDF (rather than the guide) is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FractionMode {
    /// A constant alpha everywhere (the paper uses 0.5).
    Fixed(f32),
    /// Alpha learned per spatial leaf (2019 improvement), trained with Adam on `loss`.
    Learned {
        /// Loss to minimise.
        loss: FractionLoss,
    },
}

impl Default for FractionMode {
    fn default() -> Self {
        FractionMode::Fixed(0.5)
    }
}

/// Adam hyper-parameters for the learned fraction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamConfig {
    /// Learning rate (0.01).
    pub learning_rate: f64,
    /// First-moment decay (0.9).
    pub beta1: f64,
    /// Second-moment decay (0.999).
    pub beta2: f64,
    /// Denominator epsilon (1e-8).
    pub epsilon: f64,
    /// L2 regularisation factor on theta (0.01).
    pub l2: f64,
    /// Record weight per Adam step (1.0: one step per record, as \[G\] takes them). At each
    /// `step_fractions` a leaf takes one step per this much weight recorded since its last
    /// step, none while that weight is at most this (see [`crate::fraction`]).
    pub min_batch_weight: f64,
    /// Per-record gradient magnitude clamp (1e12) before fixed-point accumulation.
    pub gradient_clamp: f64,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            learning_rate: 0.01,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            l2: 0.01,
            min_batch_weight: 1.0,
            gradient_clamp: 1e12,
        }
    }
}

/// All parameters of the SD-tree guide. `Default` gives the 2017 paper's setup.
#[derive(Clone, Debug, PartialEq)]
pub struct GuideConfig {
    /// S-tree split constant c: a leaf splits when `W > c * sqrt(2^k * spp_per_pass / 4)`
    /// (default 12000).
    pub s_tree_threshold: f64,
    /// D-tree refinement threshold rho on the energy fraction of a cell (default 0.01).
    pub d_tree_threshold: f64,
    /// Maximum quadtree depth (default and maximum 20).
    pub max_d_tree_depth: u32,
    /// Samples per pixel per pass (default 4); enters the split threshold and the schedule.
    pub spp_per_pass: u32,
    /// Spatial recording filter (default nearest).
    pub spatial_filter: SpatialFilter,
    /// Directional recording filter (default nearest).
    pub directional_filter: DirectionalFilter,
    /// BSDF-sampling fraction (default fixed 0.5).
    pub bsdf_sampling_fraction: FractionMode,
    /// Clamp applied to the learned alpha when it is used for sampling (default [0.05, 0.95]).
    pub fraction_clamp: (f32, f32),
    /// Adam parameters for the learned fraction.
    pub adam: AdamConfig,
    /// Memory cap: spatial refinement stops once the S-tree has this many nodes (default none).
    pub max_nodes: Option<usize>,
    /// Memory cap on the directional quadtrees: the building quadtrees of all leaves together
    /// may have at most this many nodes after a refinement (default none). When the refinement
    /// threshold `d_tree_threshold` would make more, the refinement uses the smallest larger
    /// threshold that fits (a coarser guide, never an allocation past the cap); see
    /// [`crate::SdTree::raised_d_tree_threshold`]. A resource limit, not part of the tree's
    /// wire form.
    pub max_dtree_nodes: Option<usize>,
    /// Fraction of each iteration's statistics the next building tree starts with, in [0, 1],
    /// applied in 1/256ths (default 0: every iteration learns from its own records alone, as
    /// in the paper; see [`crate::carry`]).
    pub carry_over: f64,
}

impl Default for GuideConfig {
    fn default() -> Self {
        Self {
            s_tree_threshold: 12000.0,
            d_tree_threshold: 0.01,
            max_d_tree_depth: crate::dtree::MAX_DEPTH,
            spp_per_pass: 4,
            spatial_filter: SpatialFilter::Nearest,
            directional_filter: DirectionalFilter::Nearest,
            bsdf_sampling_fraction: FractionMode::Fixed(0.5),
            fraction_clamp: (0.05, 0.95),
            adam: AdamConfig::default(),
            max_nodes: None,
            max_dtree_nodes: None,
            carry_over: 0.0,
        }
    }
}

impl GuideConfig {
    /// The S-tree split threshold after iteration `k`: `c * sqrt(2^k * spp_per_pass / 4)`.
    pub fn split_threshold(&self, k: u32) -> f64 {
        self.s_tree_threshold * ((2f64).powi(k as i32) * self.spp_per_pass as f64 / 4.0).sqrt()
    }
}
