//! Why one cloud's features could not be computed (shared by every step's settings check).

/// Why one cloud's features could not be computed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FeatureError {
    /// A setting is out of range.
    #[error("invalid configuration: {0}")]
    InvalidConfig(&'static str),
    /// Too little data survived a step.
    #[error("{points} usable points after {stage}, need at least {needed}")]
    TooFewPoints {
        /// The step after which the count fell short.
        stage: &'static str,
        /// Points (or descriptors) left.
        points: usize,
        /// Minimum required.
        needed: usize,
    },
}
