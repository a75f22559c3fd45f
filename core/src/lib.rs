//! Fluorescent (bispectral) materials for Mitsuba 3: the physics, in pure Rust.
//!
//! This crate has no C++ and no build script; the Mitsuba plugins (the `fluo-mitsuba`
//! crate in `mitsuba/`) reach it through one cxx bridge. Dependencies run one way:
//!
//! ```text
//! interface  <-  models (one module each; Model)  <-  model  <-  {patch, reduce, upsample, bin/fluo-rs}  <-  fluo-mitsuba
//! ```
//!
//! * [`interface`]: the one trait every bispectral material implements ([`Bispectral`]).
//! * [`models`]: one module per model (Jung, quantum dots, measured matrices, their
//!   Gaussian mixtures), each with its implementation of the interface, and their closed
//!   set ([`Model`]), the only code naming every one.
//! * [`model`]: command-line materials and the closed set of fluorescent media.
//! * [`patch`], [`reduce`], [`upsample`], [`reports`]: what is computed from any material
//!   (patch colorimetry, Fichet et al.'s reduced matrices, RGB -> fluorescent
//!   upsampling, the reports).
//! * [`spectrum`], [`colour`], [`sigmoid`], [`fileio`]: data and numerics they share.
//!
//! Units: wavelengths in nm; `lambda_i` is the excitation (incident) wavelength,
//! `lambda_o` the emission (outgoing) one.
#![forbid(unsafe_code)]

mod error;
pub mod fileio;
#[cfg(test)]
mod testutil;

pub mod colour;
pub mod interface;
pub mod model;
pub mod models;
pub mod patch;
pub mod reduce;
pub mod reports;
pub mod sigmoid;
pub mod spectrum;
pub mod upsample;

pub use error::{num, shown, Error, Result};
pub use interface::Bispectral;
pub use models::Model;
