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
    /// Shorthand for [`Error::InvalidParameter`]. The value is shown readably: a
    /// number in exponent form when its plain form would be long (`1e-300`, not 300
    /// digits), and any text cut to `MAX_SHOWN_CHARS` (80) characters (see [`shown`]).
    pub fn param(name: &str, value: impl fmt::Display, valid: impl Into<String>) -> Self {
        Error::InvalidParameter { name: shown(&name), value: shown(&value), valid: valid.into() }
    }

    /// Shorthand for [`Error::Data`]; the message is bounded as in [`shown`].
    pub fn data(msg: impl Into<String>) -> Self {
        Error::Data(elide(&msg.into(), MAX_MESSAGE_CHARS))
    }
}

/// The most characters of one value (a parameter value, a token read from a file)
/// that an error message repeats; longer text is elided in the middle.
pub const MAX_SHOWN_CHARS: usize = 80;

/// The most characters of a whole [`Error::Data`] message.
pub const MAX_MESSAGE_CHARS: usize = 1000;

/// A number as error messages show it: the shortest form that round-trips, at f32
/// precision when the value is an f32 (as Mitsuba's properties are: `-0.1`, not
/// `-0.10000000149011612`), in exponent form when the plain one would be long
/// (`1e-300`, not 300 digits).
pub fn num(x: f64) -> String {
    let single = x as f32;
    let plain = if f64::from(single) == x { format!("{single}") } else { format!("{x}") };
    if plain.len() <= 12 || (x.abs() >= 1e-4 && x.abs() < 1e7) {
        plain
    } else if f64::from(single) == x {
        format!("{single:e}")
    } else {
        format!("{x:e}")
    }
}

/// `value` as error messages show it: a number through [`num`], any other text cut
/// to `MAX_SHOWN_CHARS` (80) characters so that a message never echoes unbounded input
/// (a 50 MB line of a data file, say).
pub fn shown(value: &impl fmt::Display) -> String {
    let text = value.to_string();
    match text.trim().parse::<f64>() {
        Ok(x) if !text.trim().is_empty() => num(x),
        _ => elide(&text, MAX_SHOWN_CHARS),
    }
}

/// `text` cut in the middle to at most about `max` characters, saying how long it was.
fn elide(text: &str, max: usize) -> String {
    let n = text.chars().count();
    if n <= max {
        return text.to_string();
    }
    let head: String = text.chars().take(max * 3 / 4).collect();
    let tail: String = text.chars().skip(n - max / 4).collect();
    format!("{head}…[{} characters cut]…{tail}", n - head.chars().count() - tail.chars().count())
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

/// Check that `value` is finite and inside `[lo, hi]`; error names the parameter. An end
/// counts as reached when `value` rounds to it in single precision: values set through
/// Mitsuba's `Float` parameters (`params.update()`, textures) arrive as the nearest float,
/// e.g. a documented minimum 0.01 as 0.009999999776 (it was refused).
pub(crate) fn check_range(name: &str, value: f64, lo: f64, hi: f64) -> Result<f64> {
    let at = |end: f64| value as f32 == end as f32;
    if value.is_finite() && (value >= lo || at(lo)) && (value <= hi || at(hi)) {
        Ok(value)
    } else {
        Err(Error::param(name, value, format!("[{}, {}]", num(lo), num(hi))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_ends_reached_in_single_precision_are_inside() {
        // 0.01 and 0.3 as Mitsuba's Float holds them lie just outside [0.01, 0.3] in f64.
        assert!(check_range("width", f64::from(0.01f32), 0.01, 100.0).is_ok());
        assert!(check_range("alpha", f64::from(0.3f32), 0.001, 0.3).is_ok());
        assert!(check_range("width", 0.0099, 0.01, 100.0).is_err());
        assert!(check_range("quantum_yield", 1.000001, 0.0, 1.0).is_err());
        assert!(check_range("quantum_yield", f64::NAN, 0.0, 1.0).is_err());
    }

    #[test]
    fn numbers_and_text_are_shown_bounded() {
        assert_eq!(num(0.5), "0.5");
        assert_eq!(num(1e-300), "1e-300");
        assert_eq!(num(3e38), "3e38");
        assert_eq!(num(f64::from(-0.1f32)), "-0.1");
        assert_eq!(num(1.0 / 3.0), "0.3333333333333333");
        let e = Error::param("temperature", 1e-300, "(0, 1e4]");
        assert_eq!(e.to_string(), "invalid parameter \"temperature\" = 1e-300: valid range is (0, 1e4]");
        let long = "x".repeat(50_000_000);
        let e = Error::data(format!("line 3: cannot read '{long}'"));
        assert!(e.to_string().len() < 2 * MAX_MESSAGE_CHARS, "{}", e.to_string().len());
        assert!(Error::param("name", &long, "text").to_string().len() < 4 * MAX_SHOWN_CHARS);
    }
}
