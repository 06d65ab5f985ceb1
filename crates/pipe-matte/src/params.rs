//! Tunable thresholds of the matting pipeline.

/// Thresholds of [`crate::matte`]. `Default` holds the values tuned on the synthetic
/// PAC-NeRF scenes (200x200 and 2x downscaled).
#[derive(Debug, Clone, PartialEq)]
pub struct MatteParams {
    /// A pixel is a change candidate iff `max_c |I_c - B_c|` exceeds this (8-bit units), or
    /// 4σ where the image's noise against its plate, σ, is larger (`score.rs`). Absorbs the
    /// path tracer's noise between frame and plate.
    pub change_threshold: u8,
    /// A pixel within `change_threshold` is still a change candidate when, in some channel,
    /// both its own signed difference `I_c − B_c` and its 3×3 block's mean of it exceed this
    /// (or 4σ/3) with the same sign (8-bit units): a change a whole block shares (an object a
    /// few levels off the plate's colour) stands out of per-pixel noise three times better,
    /// and a background pixel beside the outline is not taken by its neighbours. Such a
    /// pixel's shadow test uses the block's mean colours. Values not below
    /// `change_threshold` disable it.
    pub block_change_threshold: u8,
    /// Offset `k` in the shadow ratio `(I_c + k) / (B_c + k)`; keeps near-black pixels
    /// from producing huge log-ratios. Non-positive values are treated as tiny.
    pub ratio_offset: f32,
    /// A changed pixel is shadow only if its per-channel log-ratios
    /// `l_c = ln((I_c + k) / (B_c + k))` differ by less than this (`max_c l_c - min_c l_c`):
    /// a shadow dims all channels by a similar factor.
    pub shadow_max_spread: f32,
    /// A changed pixel is shadow only if also its mean log-ratio `mean_c l_c` is below
    /// this: a shadow darkens (or keeps) the plate, it never brightens it.
    pub shadow_max_log_gain: f32,
    /// Apply the 3x3 majority vote (removes speckles, smooths the outline).
    pub majority_filter: bool,
    /// Object components (4-connected) smaller than this many pixels are dropped
    /// (one 200x200 object covers ~2000 pixels, ~500 after a 2x downscale).
    pub min_component_area: usize,
    /// Background holes enclosed by object with at most this many pixels are filled.
    /// Keep it small: real holes (a torus seen face-on) must survive.
    pub max_hole_area: usize,
    /// Outline pixels (object pixels with a background 4-neighbour) are kept only if
    /// `max_c |I_c - B_c| > boundary_change_threshold`; values not above
    /// `change_threshold` disable the peel.
    pub boundary_change_threshold: u8,
}

impl Default for MatteParams {
    fn default() -> Self {
        Self {
            change_threshold: 12,
            block_change_threshold: 4,
            ratio_offset: 4.0,
            shadow_max_spread: 0.15,
            shadow_max_log_gain: 0.05,
            majority_filter: true,
            min_component_area: 20,
            max_hole_area: 4,
            boundary_change_threshold: 24,
        }
    }
}

/// Thresholds of the multi-view steps of [`crate::matte_frame`].
#[derive(Debug, Clone, PartialEq)]
pub struct MultiViewParams {
    /// Per-view thresholds.
    pub view: MatteParams,
    /// A shadow-like pixel is tested against the other views only if its change
    /// `max_c |I_c - B_c|` exceeds this (8-bit units; default 3× the change threshold): fainter
    /// ones (penumbrae, whose edge one view may place a pixel off) stay shadow.
    pub ground_min_change: u8,
    /// A shadow-like pixel is object when at least this many other views see the ground point
    /// behind it unchanged (lit): a shadow on the ground darkens it from every side.
    pub ground_lit_views: usize,
    /// Rounds of the photo-consistency test on the pixels left ambiguous (each round's new
    /// object pixels support the next's); 0 skips it.
    pub photo_rounds: usize,
    /// An ambiguous pixel is object when this many other views see a definite object pixel
    /// of its colour where its ray meets the hull of their changed pixels.
    pub support_views: usize,
    /// Colour tolerance of that test, 8-bit levels per channel.
    pub photo_tolerance: u8,
    /// Voxels along the longest edge of the box the hulls (of the changed pixels, and for the
    /// agreement) are carved in.
    pub hull_grid: usize,
    /// Views a voxel of the agreement hull (of the other views than the one scored) may miss.
    pub hull_max_misses: usize,
    /// A mask whose [`crate::consistency`] is below this disagrees with the other views (the
    /// sample scenes' masks score 0.95 and more, a mask torn in half 0.35–0.71); below it,
    /// `consistency` also looks for one view that alone lowers the others.
    pub consistency_threshold: f64,
    /// Rounds of the graph-cut refinement (`refine.rs`); 0 skips it.
    pub cut_rounds: usize,
    /// Weight λ of the cut's contrast-sensitive smoothness term (cost units per pixel of
    /// outline across a flat region).
    pub cut_smoothness: f32,
    /// Cost of labelling a proven object pixel background, or an unchanged pixel object.
    pub cut_evidence_cost: f32,
    /// Cost of labelling a shadow-like pixel object when nothing else is known of it.
    pub cut_shadow_cost: f32,
    /// Added to that cost when a view sees its ground point dimmed the same way.
    pub cut_agree_cost: f32,
    /// Taken off that cost when `witness_min_disagree` views, and none agreeing, see its
    /// ground point dimmed otherwise, and its ray meets the other views' hull high enough.
    pub cut_pull: f32,
    /// Largest mean difference of log-dimming over a 3×3 block that agrees (`witness.rs`).
    pub witness_tolerance: f32,
    /// The tolerance grows by this many times the witness's own mean absolute deviation of
    /// log-dimming over the block: noise in a dark shadow is no disagreement.
    pub witness_noise_factor: f32,
    /// Disagreeing unoccluded views a pull needs.
    pub witness_min_disagree: usize,
    /// A pull also needs the pixel's ray to meet the hull of the other views' changed pixels
    /// this many voxels above the ground (a contact shadow's ray meets it lower).
    pub witness_min_height: f64,
    /// Half-width (pixels) of the window in which `texture.rs` fits the planes that ask
    /// whether the plate's texture shows through a shadow-like pixel.
    pub texture_radius: usize,
    /// A window whose plate, detrended, varies less than this (variance of the log-intensity)
    /// has no texture to show: its pixel gets no texture term (nor does a pixel whose own
    /// plate residual is below the window's standard deviation).
    pub texture_min_plate_variance: f32,
    /// Score of the plate's texture in the image (`texture.rs`: 1 shown at full contrast, 0
    /// hidden) at which the texture term changes sign: below it object, above it shadow.
    pub texture_split: f32,
    /// Score difference over which the texture term reaches its full weight.
    pub texture_scale: f32,
    /// Full weight of the texture term in the cost of labelling a shadow-like pixel object
    /// (0 disables it).
    pub cut_texture_cost: f32,
    /// Largest angle of the light from the vertical, degrees: the object's shadow falls no
    /// farther from a point at height `h` than `h · tan` of it (`reach.rs`).
    pub shadow_max_zenith_deg: f64,
}

impl Default for MultiViewParams {
    fn default() -> Self {
        Self {
            view: MatteParams::default(),
            ground_min_change: 36,
            ground_lit_views: 1,
            photo_rounds: 1,
            support_views: 2,
            photo_tolerance: 8,
            hull_grid: 64,
            hull_max_misses: 0,
            consistency_threshold: 0.9,
            cut_rounds: 3,
            cut_smoothness: 0.8,
            cut_evidence_cost: 2.0,
            cut_shadow_cost: 5.0,
            cut_agree_cost: 2.0,
            cut_pull: 5.25,
            witness_tolerance: 0.1,
            witness_noise_factor: 0.5,
            witness_min_disagree: 3,
            witness_min_height: 3.0,
            texture_radius: 2,
            texture_min_plate_variance: 0.002,
            texture_split: 0.5,
            texture_scale: 0.3,
            cut_texture_cost: 2.0,
            shadow_max_zenith_deg: 75.0,
        }
    }
}
