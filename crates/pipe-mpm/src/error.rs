//! Typed errors of the simulator.

/// Everything that can go wrong when building or running a simulation.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MpmError {
    /// The particle set is empty.
    #[error("empty particle set: at least one particle is required")]
    EmptyParticles,
    /// Per-particle arrays have different lengths.
    #[error("field `{field}` has {len} entries, expected {expected} (one per particle)")]
    LengthMismatch {
        /// Field name.
        field: &'static str,
        /// Its length.
        len: usize,
        /// The particle count.
        expected: usize,
    },
    /// A value is NaN or infinite.
    #[error("field `{field}` of particle {index} is not finite ({value})")]
    NonFiniteInput {
        /// Field name.
        field: &'static str,
        /// Particle index (0 for scalars).
        index: usize,
        /// The offending value.
        value: f64,
    },
    /// A parameter is outside its valid range.
    #[error("invalid `{field}` = {value}: {reason}")]
    InvalidParameter {
        /// Parameter name.
        field: &'static str,
        /// The offending value.
        value: f64,
        /// The rule it breaks.
        reason: &'static str,
    },
    /// A per-particle parameter is outside its valid range.
    #[error("invalid `{field}` = {value} of particle {index}: {reason}")]
    InvalidParticleParameter {
        /// Parameter name.
        field: &'static str,
        /// Particle index.
        index: usize,
        /// The offending value.
        value: f64,
        /// The rule it breaks.
        reason: &'static str,
    },
    /// A position lies outside the simulation domain where one is required inside.
    #[error("particle {index} at {position:?} m lies outside the domain")]
    OutsideDomain {
        /// Particle index.
        index: usize,
        /// Its position (m).
        position: [f64; 3],
    },
    /// A user-fixed time step breaks a stability limit.
    #[error("dt = {dt:e} s exceeds the {limit} stability limit {max_dt:e} s")]
    StepTooLarge {
        /// Which limit (`"elastic wave (CFL)"`, `"viscous"`).
        limit: &'static str,
        /// The requested step.
        dt: f64,
        /// The largest stable step.
        max_dt: f64,
    },
    /// The simulation (or its backward pass) produced NaN or Inf.
    #[error("non-finite `{quantity}` of particle {particle} at substep {substep}")]
    NonFinite {
        /// Substep index (0-based, counted from the start of the run).
        substep: usize,
        /// `"x"`, `"v"`, `"C"`, `"F"` (forward) or `"dL/dx"`, ... (backward).
        quantity: &'static str,
        /// First offending particle.
        particle: usize,
    },
    /// The particles of a run whose grid follows them spread over more nodes than its budget
    /// (fragments flying apart).
    #[error(
        "at substep {substep} the particles span {lo:?} to {hi:?} m: a grid over them needs \
         {nodes} nodes at dx = {dx} m, over the budget of {budget} nodes (fragments flying \
         apart?); declare a `domain`, or a larger cell size"
    )]
    GridTooLarge {
        /// Substep index (0-based, counted from the start of the run).
        substep: usize,
        /// The particles' box (m).
        lo: [f64; 3],
        hi: [f64; 3],
        /// Nodes of the window over them, and the budget.
        nodes: usize,
        budget: usize,
        /// Cell size (m).
        dx: f64,
    },
    /// On a grid that follows the particles, a node moved more than a cell in one substep:
    /// the run has diverged (a substep far beyond the stability limit), and its particles
    /// would fly apart without bound.
    #[error(
        "the run diverged at substep {substep}: grid velocities reach {speed:.3e} m/s, {cells:.3e} \
         cells per substep (MPM needs well under one)"
    )]
    Diverged {
        /// Substep index (0-based, counted from the start of the run).
        substep: usize,
        /// Largest grid velocity component (m/s).
        speed: f64,
        /// Cells it crosses per substep.
        cells: f64,
    },
    /// Gradient buffers do not match the tape.
    #[error("gradient input mismatch: {0}")]
    GradientMismatch(&'static str),
}

impl MpmError {
    /// This error said of substep `k` (for errors that name one).
    pub(crate) fn at_substep(self, k: usize) -> Self {
        match self {
            MpmError::GridTooLarge {
                lo,
                hi,
                nodes,
                budget,
                dx,
                ..
            } => MpmError::GridTooLarge {
                substep: k,
                lo,
                hi,
                nodes,
                budget,
                dx,
            },
            MpmError::NonFinite {
                quantity, particle, ..
            } => MpmError::NonFinite {
                substep: k,
                quantity,
                particle,
            },
            other => other,
        }
    }

    /// This error of a scalar check, said of particle `index`: an invalid or non-finite value
    /// names the particle; other errors are unchanged.
    pub(crate) fn at_particle(self, index: usize) -> Self {
        match self {
            MpmError::InvalidParameter {
                field,
                value,
                reason,
            } => MpmError::InvalidParticleParameter {
                field,
                index,
                value,
                reason,
            },
            MpmError::NonFiniteInput { field, value, .. } => MpmError::NonFiniteInput {
                field,
                index,
                value,
            },
            other => other,
        }
    }
}
