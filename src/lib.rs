//! Fluorescent (bispectral) materials for Mitsuba 3.
//!
//! The physics lives here, in pure Rust, testable with `cargo test` alone. The
//! [`ffi`] module is the one place that sees the C++ side (a single `#[cxx::bridge]`);
//! the Mitsuba plugin shims in `plugins/` call through it.
//!
//! Layout (one name through every layer):
//! `src/<model>.rs` (physics) -> `src/ffi/` (bridge) -> `plugins/<plugin>.cpp` (shim)
//! -> `type="<plugin>"` in scene XML -> `tests/python/test_<plugin>.py`.
//!
//! Units: wavelengths in nm; `lambda_i` is the excitation (incident) wavelength,
//! `lambda_o` the emission (outgoing) one.

mod error;
pub mod fileio;
#[cfg(test)]
mod testutil;

pub mod bispectral;
pub mod colour;
pub mod gmm;
pub mod gmm_report;
pub mod jung;
pub mod material;
pub mod matrix;
pub mod mitsuba;
pub mod qd;
pub mod reduce;
pub mod sigmoid;
pub mod spectrum;
pub mod upsample;

#[allow(unsafe_code, missing_docs)]
pub mod ffi;

pub use error::{num, shown, Error, Result};
