//! Reports that compare models and reductions against references (printed by
//! `fluo-rs`, recorded by the benchmarks). They sit above every other module.

pub mod gmm;
pub mod reduction;
