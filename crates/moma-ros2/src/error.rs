//! Errors of message conversion and of the DDS transport.

use moma_core::ImageSize;

/// What went wrong with a message or the transport.
#[derive(Debug, thiserror::Error)]
pub enum RosError {
    /// A message whose fields contradict its data (truncated, empty, absurd sizes, bad values).
    #[error("malformed message: {0}")]
    Malformed(String),
    /// An image encoding the receiver does not take.
    #[error("unsupported image encoding {encoding:?} (expected {expected})")]
    Encoding {
        /// The encoding received.
        encoding: String,
        /// The encodings taken.
        expected: String,
    },
    /// An image or camera of another size than the one expected.
    #[error("{what} is {got}, expected {expected}")]
    Size {
        /// What has the wrong size.
        what: String,
        /// Its size.
        got: ImageSize,
        /// The size expected.
        expected: ImageSize,
    },
    /// The DDS layer refused to create an entity or to send.
    #[error("DDS: {0}")]
    Dds(String),
    /// A topic or node name ROS 2 does not accept.
    #[error("ROS 2 name {name:?}: {why}")]
    Name {
        /// The name.
        name: String,
        /// Why it was refused.
        why: String,
    },
}

impl RosError {
    /// A [`RosError::Malformed`] with this text.
    pub fn malformed(why: impl Into<String>) -> Self {
        Self::Malformed(why.into())
    }
}

/// Result with [`RosError`].
pub type Result<T> = std::result::Result<T, RosError>;
