//! Typed errors for invalid input.

/// Why a field, its optimiser or its weights rejected their input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FieldError {
    /// A domain axis has zero or negative extent (the planes cannot be laid over it).
    #[error("domain axis {axis} has extent {extent} m (min {min} m, max {max} m): it must be > 0")]
    DomainExtent {
        /// `x`, `y` or `z`.
        axis: char,
        /// Lower bound, metres.
        min: f64,
        /// Upper bound, metres.
        max: f64,
        /// `max − min`, metres.
        extent: f64,
    },
    /// A domain bound is NaN or infinite.
    #[error("domain `{field}` on axis {axis} is {value}: it must be finite")]
    DomainNotFinite {
        /// `min`, `max` or `margin`.
        field: &'static str,
        /// `x`, `y` or `z` (`-` for the margin).
        axis: char,
        /// The value received.
        value: f64,
    },
    /// A point coordinate is NaN (infinite coordinates are clamped to the box).
    #[error("`{field}`[{index}].{axis} is NaN")]
    PointNaN {
        /// Name of the point buffer.
        field: &'static str,
        /// Index of the point.
        index: usize,
        /// `x`, `y` or `z`.
        axis: char,
    },
    /// A configuration or optimiser value is out of range.
    #[error("`{field}` = {value} is invalid: {reason}")]
    Config {
        /// Name of the parameter.
        field: &'static str,
        /// The value received, formatted.
        value: String,
        /// What was expected.
        reason: &'static str,
    },
    /// A buffer does not hold the expected number of values.
    #[error("`{field}` has {got} values, expected {expected}")]
    Length {
        /// Name of the buffer.
        field: &'static str,
        /// Required value count.
        expected: usize,
        /// Value count received.
        got: usize,
    },
    /// A value of a buffer is NaN or infinite.
    #[error("`{field}`[{index}] is {value}: it must be finite")]
    NotFinite {
        /// Name of the buffer (or of the parameter group).
        field: String,
        /// Index within the buffer.
        index: usize,
        /// The value received.
        value: f64,
    },
    /// A saved weights table does not match its configuration.
    #[error("field weights, tensor `{tensor}`: {reason}")]
    Weights {
        /// Name of the tensor (e.g. `plane.xy`, `mlp.0.weight`).
        tensor: String,
        /// What is wrong.
        reason: String,
    },
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, FieldError>;

/// `x`, `y`, `z` for axis 0, 1, 2.
pub(crate) const AXES: [char; 3] = ['x', 'y', 'z'];

/// The first non-finite value of `values`, as an error naming `field`.
pub(crate) fn check_finite(field: &str, values: &[f64]) -> Result<()> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(index) => Err(FieldError::NotFinite {
            field: field.to_owned(),
            index,
            value: values[index],
        }),
    }
}

/// `got == expected`, else a length error naming `field`.
pub(crate) fn check_len(field: &'static str, expected: usize, got: usize) -> Result<()> {
    if got == expected {
        Ok(())
    } else {
        Err(FieldError::Length {
            field,
            expected,
            got,
        })
    }
}
