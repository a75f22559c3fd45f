//! The crate's error type: every constructor and loader returns it instead of panicking.

use std::fmt;

/// Errors raised when building a model or reading data.
///
/// Messages name the offending parameter, its value and the valid range, so that
/// they can be shown to a Mitsuba user verbatim (they cross the FFI as exceptions).
#[derive(Debug, Clone, PartialEq)]
pub enum Error {
    /// A parameter is outside its valid range (or not finite).
    InvalidParameter {
        /// Parameter name, as the user wrote it (e.g. `stokes_shift`).
        name: String,
        /// The offending value, formatted.
        value: String,
        /// The valid range or rule, in words (e.g. `[0, 1]`).
        valid: String,
    },
    /// Malformed input data (a file, a table, a spectrum).
    Data(String),
    /// An I/O failure, with the path involved.
    Io(String),
}

impl Error {
    /// Shorthand for [`Error::InvalidParameter`].
    pub fn param(name: &str, value: impl fmt::Display, valid: impl Into<String>) -> Self {
        Error::InvalidParameter { name: name.to_string(), value: value.to_string(), valid: valid.into() }
    }

    /// Shorthand for [`Error::Data`].
    pub fn data(msg: impl Into<String>) -> Self {
        Error::Data(msg.into())
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::InvalidParameter { name, value, valid } => {
                write!(f, "invalid parameter \"{name}\" = {value}: valid range is {valid}")
            }
            Error::Data(msg) => write!(f, "invalid data: {msg}"),
            Error::Io(msg) => write!(f, "I/O error: {msg}"),
        }
    }
}

impl std::error::Error for Error {}

/// The crate's result type.
pub type Result<T> = std::result::Result<T, Error>;

/// Check that `value` is finite and inside `[lo, hi]`; error names the parameter.
pub(crate) fn check_range(name: &str, value: f64, lo: f64, hi: f64) -> Result<f64> {
    if value.is_finite() && value >= lo && value <= hi {
        Ok(value)
    } else {
        Err(Error::param(name, value, format!("[{lo}, {hi}]")))
    }
}
