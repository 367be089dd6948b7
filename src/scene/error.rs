//! One error type for everything that reads or writes scenes and cameras.

use std::path::PathBuf;

/// Why a scene or camera file was rejected. Every variant carries a message a user understands;
/// readers return one of these before any large allocation and never panic on bad input.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("i/o error: {0}")]
    IoPlain(#[from] std::io::Error),
    #[error("unknown scene format: {0}")]
    UnknownFormat(String),
    #[error("malformed header: {0}")]
    Header(String),
    #[error(
        "file is truncated: the header declares {expected} bytes of data but only {actual} are present"
    )]
    Truncated { expected: u64, actual: u64 },
    #[error("sizes in the header overflow: {0}")]
    Overflow(String),
    #[error("list property '{0}' is not supported in a Gaussian splat file")]
    ListProperty(String),
    #[error("element '{0}' is declared more than once")]
    DuplicateElement(String),
    #[error("property '{0}' is declared more than once")]
    DuplicateProperty(String),
    #[error("required property '{0}' is missing")]
    MissingProperty(String),
    #[error("'{name}' is missing from {place}")]
    MissingFile { name: String, place: String },
    #[error("Gaussian {index}: {field} is NaN or infinite")]
    NonFinite { index: usize, field: &'static str },
    #[error("Gaussian {index}: rotation quaternion has zero length")]
    ZeroQuaternion { index: usize },
    #[error("scene has {count} Gaussians, more than the configured maximum of {max}")]
    TooManyGaussians { count: u64, max: usize },
    #[error("spherical-harmonics degree {0} is not supported (0 to 3 are)")]
    UnsupportedShDegree(usize),
    #[error(
        "{0} f_rest properties do not match a spherical-harmonics degree (0, 9, 24 or 45 expected)"
    )]
    ShRestCount(usize),
    #[error("file is {size} bytes, more than the configured maximum of {max} bytes")]
    FileTooLarge { size: u64, max: u64 },
    #[error("unsupported: {0}")]
    Unsupported(String),
    #[error("corrupt data: {0}")]
    Corrupt(String),
    #[error("corrupt data: the {0} does not match the data")]
    Checksum(&'static str),
    #[error("inconsistent scene: {0}")]
    Inconsistent(String),
    #[error("bad camera file: {0}")]
    Camera(String),
}
