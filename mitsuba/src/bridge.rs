//! The C++ bridge: the one `#[cxx::bridge]` module, and the only code that sees cxx.
//!
//! Direction: C++ (the Mitsuba plugin shims in `plugins/`, headers in `include/fluo/`)
//! calls Rust; Rust never calls C++. Models cross as opaque `Box`es. Construction returns
//! `Result`, which cxx turns into a C++ exception carrying the Rust message; the shims
//! rethrow it through Mitsuba's `Throw`. No panic may cross: constructors run under
//! `catch_unwind` ([`guarded`]), and hot-path functions are written without panicking
//! operations (iterators, no indexing). Spectra cross as slices of `f32` wavelengths (nm)
//! and values, one entry per hero wavelength.
//!
//! # Order
//! One section per plugin, in the same order in the bridge declaration and in the
//! implementations below it, each headed by a comment:
//! 1. shared value types ([`Rgb`], [`Range`], [`Sample`], [`Vec3`]) and helpers;
//! 2. `fluo_illuminant`: [`Illuminant`];
//! 3. `fluo_jung`: [`JungModel`], its colour upsampling cube ([`UpsampleCube`]) and
//!    per-texel models ([`JungTexture`]);
//! 4. `fluo_qd`: [`QdModel`]; the media `fluo_qd_medium`, `fluo_dye_medium`: [`FluoMedium`];
//! 5. `fluo_matrix`, `fluo_gmm` (measured materials): [`MeasuredModel`];
//! 6. what the `fluo_path` integrator needs: the generic [`Fluorescence`] handle and the
//!    reduced (matrix-throughput) RGB transport, [`TransportBasis`] and [`ReducedModel`].
//!
//! # One home per model
//! Each model is stored once. The integrator sees every material through the generic
//! [`Fluorescence`] handle, a [`fluo::Model`] (static dispatch over the closed set)
//! whose variants hold the concrete model behind an `Arc`. A plugin handle that needs
//! the concrete model (`JungModel`, `QdModel`) keeps a second `Arc` to that same model
//! next to its generic handle, so typed access needs no `match` and the generic handle
//! is borrowed from the plugin handle (`jung_fluorescence`, `qd_fluorescence`). A
//! measured material needs nothing beyond the interface, so its generic handle is its
//! only field.

// This crate is the foreign-function boundary: cxx generates unsafe glue, and the
// registration marker below is an unmangled C symbol. The physics (`fluo`) forbids
// unsafe code.
#![allow(unsafe_code, missing_docs)]

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Arc;

use fluo::colour::bounded_rgb_albedo;
use fluo::colour::mitsuba::{spectrum_to_srgb, CIE_MAX_NM, CIE_MIN_NM};
use fluo::interface::Bispectral;
use fluo::model::{MediumModel, Model};
use fluo::models::jung::{DyeMedium, DyeMediumParams, JungFluorescence, JungParams, Reflectance};
use fluo::models::qd;
use fluo::reduce::{Method, Operator, Transport};
use fluo::sigmoid::SigmoidPolynomial;
use fluo::spectrum::{cmf, illuminant, IrregularSpectrum, Observer, Spectral};

#[cxx::bridge(namespace = "fluo")]
mod bridge {
    // ------------------------------------------------------------ shared value types

    /// A linear sRGB triple (Mitsuba's RGB variants' working space).
    struct Rgb {
        r: f64,
        g: f64,
        b: f64,
    }

    /// A closed wavelength interval, nm; empty when `lo >= hi`.
    struct Range {
        lo: f64,
        hi: f64,
    }

    /// A sampled wavelength with its pdf (per nm); `pdf == 0` means no sample.
    struct Sample {
        value: f64,
        pdf: f64,
    }

    /// A unit direction in the local shading frame (z = normal).
    struct Vec3 {
        x: f64,
        y: f64,
        z: f64,
    }

    extern "Rust" {
        /// Record a plugin the library registers with Mitsuba (`kind`: `bsdf`,
        /// `integrator`, `texture`, `medium`; `vectorised`: also served in the llvm/cuda
        /// variants), for `fluo_plugin_list`.
        fn note_plugin(name: &str, kind: &str, vectorised: bool);
    }

    // -------------------------------------------------------------- fluo_illuminant

    extern "Rust" {
        /// An emission spectrum for `fluo_illuminant`: a CIE illuminant or a CSV file.
        type Illuminant;

        /// `name` (a CIE illuminant) or `filename` (a `nm,value` CSV), exactly one
        /// non-empty; with `normalize`, scaled so that its luminance ∫ I ȳ / ∫ ȳ
        /// (CIE 1931) is `scale`, otherwise multiplied by `scale`.
        fn illuminant_new(name: &str, filename: &str, scale: f64, normalize: bool) -> Result<Box<Illuminant>>;
        fn illuminant_eval(s: &Illuminant, lambdas: &[f32], out: &mut [f32]);
        /// Its nodes (nm) and values, scale applied: linearly interpolated and zero
        /// outside, they are the spectrum, so the shim can hand them to Mitsuba's own
        /// `regular`/`irregular` spectrum for per-sample evaluation.
        fn illuminant_nodes(s: &Illuminant, wavelengths: &mut Vec<f64>, values: &mut Vec<f64>);
        /// The wavelengths where it is defined, nm.
        fn illuminant_range(s: &Illuminant) -> Range;
        /// Mean value over Mitsuba's 360–830 nm.
        fn illuminant_mean(s: &Illuminant) -> f64;
        /// Linear sRGB (Mitsuba's convention) for the RGB variant, negative channels clipped.
        fn illuminant_srgb(s: &Illuminant) -> Rgb;
        fn illuminant_to_string(s: &Illuminant) -> String;
        /// Whether most of its radiant power lies below `UV_EDGE_NM` (a UV lamp: reduced
        /// RGB transport carries it in one UV band and misstates UV-excited fluorescence
        /// by up to ~5x, see `fluo-rs saturated-report`).
        fn illuminant_is_mostly_uv(s: &Illuminant) -> bool;
    }

    // --------------------------------------------------------------------- fluo_jung

    /// `fluo_jung` parameters as parsed from Mitsuba `Properties` by the shim (or looked
    /// up in a coefficient cube).
    struct JungConfig {
        emission_peak: f64,
        stokes_shift: f64,
        concentration: f64,
        quantum_yield: f64,
        /// True when the reflectance is given as sigmoid `coefficients`
        /// (otherwise the shim evaluates a Mitsuba texture itself).
        has_coefficients: bool,
        /// Sigmoid-polynomial coefficients for λ in nm.
        c0: f64,
        c1: f64,
        c2: f64,
    }

    /// RGB variant (linear sRGB under E, Mitsuba's conversion) of one `fluo_jung` model,
    /// split so that a textured concentration c and yield Q apply per hit:
    /// elastic = `reflectance` − c·`reflectance_absorbed` (sigmoid base) or texture ⊙
    /// (1 − c·`absorbed_scale`), reradiation = c·Q·`fluorescence`.
    struct JungRgbParts {
        /// sRGB[r(λ)].
        reflectance: Rgb,
        /// sRGB[r(λ)·a(λ)].
        reflectance_absorbed: Rgb,
        /// sRGB[a(λ)] / sRGB[1] per channel.
        absorbed_scale: Rgb,
        /// sRGB[e(λ)·∫a] with ∫ over 360–830 nm (the reradiation at c = Q = 1).
        fluorescence: Rgb,
    }

    extern "Rust" {
        /// A validated, baked `fluo_jung` material.
        type JungModel;

        fn jung_new(config: &JungConfig) -> Result<Box<JungModel>>;
        /// The plugin defaults (those of `JungParams::default()`), reflectance from a texture.
        fn jung_default_config() -> JungConfig;
        fn jung_is_fluorescent(model: &JungModel) -> bool;
        /// out[j] = 1 − c·a(λ_j).
        fn jung_elastic_factor(model: &JungModel, lambdas: &[f32], out: &mut [f32]);
        /// out[j] = r(λ_j)·(1 − c·a(λ_j)) for sigmoid reflectance (0 without coefficients).
        fn jung_elastic_albedo(model: &JungModel, lambdas: &[f32], out: &mut [f32]);
        /// RGB variant, sigmoid reflectance: sRGB of the spectrum reflected under E,
        /// bounded to [0, 1] per channel (`fluo::colour::bounded_rgb_albedo`).
        fn jung_rgb_albedo(model: &JungModel) -> Rgb;
        /// RGB variant: sRGB of the elastic part r(λ)(1 − c a(λ)) under E (unclamped).
        fn jung_rgb_elastic(model: &JungModel) -> Rgb;
        /// RGB variant: an elastic albedo plus a reradiated one, bounded to [0, 1] per
        /// channel by scaling the reradiation (`fluo::colour::bounded_rgb_albedo`).
        fn rgb_bounded_albedo(elastic: Rgb, reradiated: Rgb) -> Rgb;
        /// RGB variant, texture reflectance: per-channel elastic scale sRGB(1 − c a)/sRGB(1).
        fn jung_rgb_elastic_scale(model: &JungModel) -> Rgb;
        /// RGB variant: sRGB of the reradiated spectrum under E, c Q e(λ) ∫ a.
        fn jung_rgb_fluorescence(model: &JungModel) -> Rgb;
        fn jung_to_string(model: &JungModel) -> String;
        /// The model's fluorescent part, for the integrator.
        fn jung_fluorescence(model: &JungModel) -> &Fluorescence;

        /// An RGB -> (reflectance + fluorescence) coefficient cube (`core/src/upsample/`).
        type UpsampleCube;

        /// Load the cube for `space` ("srgb", "rec2020", "acescg"): `filename`, or the
        /// shipped `data/cubes/<space>_d65_tinf_r33.cube` when empty. Errors for an
        /// unknown space, a malformed file, or a cube of another space.
        fn upsample_cube_load(space: &str, filename: &str) -> Result<Box<UpsampleCube>>;
        fn upsample_cube_describe(cube: &UpsampleCube) -> String;
        /// The `fluo_jung` configuration of `rgb` (3 values in [0, 1]): sigmoid
        /// coefficients and dye; `lookup` is "nearest" or "trilinear"; `fluorescence =
        /// false` uses the reflectance-only solutions.
        fn upsample_lookup(cube: &UpsampleCube, rgb: &[f64], lookup: &str, fluorescence: bool) -> Result<JungConfig>;

        /// Per-texel `fluo_jung` models of an RGB texture, built once at load.
        type JungTexture;

        /// `rgb`: width·height·3 floats, row-major from the top row (Mitsuba's texel
        /// order). Errors name the first NaN or out-of-range texel.
        fn jung_texture_new(
            cube: &UpsampleCube,
            width: usize,
            height: usize,
            rgb: &[f32],
            lookup: &str,
            fluorescence: bool,
        ) -> Result<Box<JungTexture>>;
        /// The model of texel (x, y) (wrapped into range).
        fn jung_texture_model(tex: &JungTexture, x: i64, y: i64) -> &JungModel;
        /// RGB variant: the texel's albedo, sRGB of the reflected spectrum under E.
        fn jung_texture_rgb(tex: &JungTexture, x: i64, y: i64) -> Rgb;
        /// A texel model that fluoresces with the longest emission (for scene scans),
        /// or any texel's when none fluoresces.
        fn jung_texture_representative(tex: &JungTexture) -> &JungModel;
        fn jung_texture_is_fluorescent(tex: &JungTexture) -> bool;
        /// Distinct coefficient sets among the texels.
        fn jung_texture_distinct(tex: &JungTexture) -> usize;
        /// The configuration a model was built from (the vectorised shim bakes texels'
        /// parameters into arrays from it).
        fn jung_config(model: &JungModel) -> JungConfig;

        // Textured numeric parameters (`emission_peak`, `stokes_shift`,
        // `concentration`, `quantum_yield`). The reradiation is linear in c·Q and the
        // elastic factor 1 − c·a(λ) linear in c, so a vertex needs one dye *shape* per
        // (λe, s) pair, built once at load with c = Q = 1, and its own c and Q.

        /// Check every value of a parameter texture on its own
        /// (`fluo::models::jung::check_param_value`): `width` > 0 names a failing value by
        /// its texel (x, y), row-major from the top row; 0 by its position in `values`.
        fn jung_check_values(name: &str, values: &[f32], width: usize) -> Result<()>;
        /// out[j] = a(λ_j), the absorption (peak 1).
        fn jung_absorption(model: &JungModel, lambdas: &[f32], out: &mut [f32]);
        /// out[j] = r(λ_j), the sigmoid base reflectance (0 without coefficients).
        fn jung_reflectance(model: &JungModel, lambdas: &[f32], out: &mut [f32]);
        /// RGB variant: the c-linear parts of an albedo (see [`JungRgbParts`]) with the
        /// dye of `dye` and the sigmoid base reflectance of `base`.
        fn jung_rgb_parts(dye: &JungModel, base: &JungModel) -> JungRgbParts;

        /// The dye shapes (c = Q = 1, no base reflectance) of every pair of the
        /// textured emission peaks and Stokes shifts, index i·len(shifts) + j.
        type JungShapes;

        /// Errors name the first (λe, s) pair that is not a valid dye, and a pair count
        /// above `MAX_JUNG_SHAPES`.
        fn jung_shapes_new(peaks: &[f64], shifts: &[f64]) -> Result<Box<JungShapes>>;
        fn jung_shapes_len(shapes: &JungShapes) -> usize;
        fn jung_shapes_model(shapes: &JungShapes, i: usize) -> &JungModel;
        /// The shape with the longest emission (for scene scans).
        fn jung_shapes_representative(shapes: &JungShapes) -> usize;
    }

    // ----------------------------------------------------------------------- fluo_qd

    /// The Brus-equation and Stokes-shift constants of `fluo_qd` (the paper's Table 1),
    /// SI units: `fluo::models::qd::QdConstants`.
    struct QdConstants {
        gap_energy: f64,
        elementary_charge: f64,
        planck: f64,
        light_speed: f64,
        boltzmann: f64,
        electron_mass: f64,
        hole_mass: f64,
        vacuum_permittivity: f64,
        relative_permittivity: f64,
        temperature: f64,
    }

    /// `fluo_qd` in the vectorised variants: what the shim interpolates per lane
    /// (`fluo::models::qd::JitTables`, whose docs say what each holds; the excitation
    /// support is empty, lo ≥ hi, when the coating never re-emits).
    struct QdJitTables {
        lambda: Vec<f64>,
        rows: usize,
        a_tot: Vec<f64>,
        cdf: Vec<f64>,
        r_spe: Vec<f64>,
        pass: Vec<f64>,
        r_tot: Vec<f64>,
        extra_r_spe: Vec<f64>,
        extra_pass: Vec<f64>,
        emission_peak_nm: f64,
        emission_scale_nm: f64,
        emission_norm: f64,
        lambda_min: f64,
        lambda_max: f64,
        excitation_lo: f64,
        excitation_hi: f64,
    }

    /// `fluo_qd_medium` / `fluo_dye_medium` in the vectorised variants: what the shim
    /// interpolates per lane (`fluo::model::MediumJitTables`, whose docs say what each holds).
    struct MediumJitTables {
        lambda: Vec<f64>,
        mu_a: Vec<f64>,
        cum: Vec<f64>,
        emission_lambda: Vec<f64>,
        emission: Vec<f64>,
    }

    /// `fluo_qd` parameters as parsed from Mitsuba `Properties` by the shim:
    /// `fluo::models::qd::QdParams` under the plugin's parameter names.
    struct QdConfig {
        radius: f64,
        width: f64,
        quantum_yield: f64,
        density: f64,
        ext_ior: f64,
        lambda_min: f64,
        lambda_max: f64,
        /// GGX if true, Beckmann otherwise.
        ggx: bool,
        alpha: f64,
        constants: QdConstants,
        /// Rows of the excitation tables, uniform in cos θ.
        table_cos_nodes: usize,
        /// Base λ step of the excitation tables, nm.
        table_step: f64,
    }

    /// A spectrum sampled by the shim, borrowed for one call: one value is a constant
    /// (its wavelength is ignored), several a table (nm, ascending) evaluated linearly
    /// and constant beyond its ends.
    struct SampledSpectrum<'a> {
        wavelengths: &'a [f64],
        values: &'a [f64],
    }

    extern "Rust" {
        /// A validated, baked `fluo_qd` material.
        type QdModel;

        /// Substrate η and k relative to the environment, each on its own grid; QD index
        /// n and k (both empty: built-in CdSe).
        fn qd_new(
            config: &QdConfig,
            eta: &SampledSpectrum,
            k: &SampledSpectrum,
            qd_eta: &SampledSpectrum,
            qd_k: &SampledSpectrum,
        ) -> Result<Box<QdModel>>;
        /// The plugin defaults (those of `QdParams::default()` and Table 1).
        fn qd_default_config() -> QdConfig;
        fn qd_is_fluorescent(model: &QdModel) -> bool;
        /// Coating coefficients at the microfacet cosine for each λ: the film's R_spe and
        /// the two-pass transmission T_spe²(1 − A_tf)², so that
        /// R_tot = R_spe + pass·R / (1 − R·R_spe) for substrate reflectance R (eq. 23).
        fn qd_elastic_coefficients(
            model: &QdModel,
            cos_theta: f32,
            lambdas: &[f32],
            r_spe: &mut [f32],
            pass: &mut [f32],
        );
        /// The tables of [`QdJitTables`] at `rows` cosines, with the coating's
        /// coefficients also at `extra_nm` (the RGB channels' wavelengths).
        fn qd_jit_tables(model: &QdModel, rows: usize, lambda: &[f64], extra_nm: &[f64]) -> QdJitTables;
        fn qd_to_string(model: &QdModel) -> String;
        /// The coating's bispectral part, for the integrator.
        fn qd_fluorescence(model: &QdModel) -> &Fluorescence;
        /// Check every value of a `radius`, `density`, `quantum_yield` or `alpha` texture on its own
        /// (`fluo::models::qd::check_param_value`; `width` as for `jung_check_values`).
        fn qd_check_values(name: &str, values: &[f32], width: usize) -> Result<()>;
        /// `fluo::models::qd::TEXTURE_GRID_NODES`: density nodes of a textured coating.
        fn qd_texture_grid_nodes() -> usize;
        /// `fluo::models::qd::TEXTURE_MAX_RADII`: most radii a radius texture may hold.
        fn qd_texture_max_radii() -> usize;
        /// `fluo::models::qd::TEXTURE_MAX_ALPHAS`: most roughnesses an alpha texture may hold.
        fn qd_texture_max_alphas() -> usize;
    }

    // ------------------------------------------- fluo_qd_medium, fluo_dye_medium

    /// `fluo_qd_medium` parameters as parsed by the shim:
    /// `fluo::models::qd::QdMediumParams` under the plugin's parameter names.
    struct QdMediumConfig {
        radius: f64,
        width: f64,
        quantum_yield: f64,
        /// Molar concentration of dots, µmol/L.
        concentration: f64,
        ext_ior: f64,
        lambda_min: f64,
        lambda_max: f64,
        constants: QdConstants,
        table_step: f64,
    }

    /// `fluo_dye_medium` parameters: `fluo::models::jung::DyeMediumParams`.
    struct DyeMediumConfig {
        emission_peak: f64,
        stokes_shift: f64,
        quantum_yield: f64,
        /// Peak absorption coefficient, 1/m.
        sigma_a: f64,
    }

    extern "Rust" {
        /// A validated fluorescent participating medium (`fluo::model::MediumModel`),
        /// coefficients per metre at density 1.
        type FluoMedium;

        fn qd_medium_new(config: &QdMediumConfig) -> Result<Box<FluoMedium>>;
        /// The plugin defaults (those of `QdMediumParams::default()`).
        fn qd_medium_default_config() -> QdMediumConfig;
        fn dye_medium_new(config: &DyeMediumConfig) -> Result<Box<FluoMedium>>;
        /// The plugin defaults (those of `DyeMediumParams::default()`).
        fn dye_medium_default_config() -> DyeMediumConfig;
        fn medium_is_fluorescent(model: &FluoMedium) -> bool;
        /// out[j] = μa(λ_j), 1/m.
        fn medium_absorption(model: &FluoMedium, lambdas: &[f32], out: &mut [f32]);
        /// RGB variants: μa as Mitsuba turns a spectrum into linear sRGB
        /// (`spectrum_to_srgb`), negative channels clipped to 0, 1/m.
        fn medium_absorption_rgb(model: &FluoMedium) -> Rgb;
        /// [λmin, λmax], nm: where absorption re-emits and where emission lands.
        fn medium_lambda_range(model: &FluoMedium) -> Range;
        /// out[j] = μf(λo_j) = ∫_R μa(λi) f(λi → λo_j) dλi, 1/m.
        fn medium_shift_coefficients(model: &FluoMedium, lambdas: &[f32], range: &Range, out: &mut [f32]);
        /// For each λo_j: mu_f[j] = μf(λo_j | R) (1/m) and samples[j] = λi with density
        /// μa f / μf over the excitation interval of λo_j in R, drawn with xis[j] (pdf 0:
        /// none); one call per fluorescent collision.
        fn medium_shift_and_sample(
            model: &FluoMedium,
            lambdas: &[f32],
            xis: &[f64],
            range: &Range,
            mu_f: &mut [f32],
            samples: &mut [Sample],
        );
        fn medium_to_string(model: &FluoMedium) -> String;
        /// The tables of [`MediumJitTables`] (vectorised variants).
        fn medium_jit_tables(model: &FluoMedium) -> MediumJitTables;
    }

    // ----------------------------------------------------- fluo_matrix, fluo_gmm

    /// A measured material's tables for the vectorised variants, which evaluate them per
    /// lane (Dr.Jit cannot call Rust at render time): the diagonal always, then either
    /// the matrix's tables (`fluo_matrix`) or the mixture (`fluo_gmm`). See
    /// `core/src/models/matrix.rs` and `gmm.rs` for the functions they define.
    struct MeasuredTables {
        /// "matrix" or "gmm".
        kind: String,
        /// ρ at `diagonal_nm` (interpolated linearly, constant beyond the ends).
        diagonal_nm: Vec<f64>,
        diagonal: Vec<f64>,
        /// matrix: the λi and λo grids, nm.
        lambda_i: Vec<f64>,
        lambda_o: Vec<f64>,
        /// matrix: P at the nodes, nm⁻¹, `p[j·n_i + k]` = P(λi_k, λo_j) (bilinear between
        /// nodes, zero for λi > λo), and the running integrals of its rows over λi.
        p: Vec<f64>,
        row_cdf: Vec<f64>,
        /// gmm: S, nm.
        scale: f64,
        /// gmm: the measured rectangle [λi_min, λi_max, λo_min, λo_max], nm.
        rect: Vec<f64>,
        /// gmm: six numbers per component, π, μi, μo, σii, σio, σoo (σio symmetrised).
        components: Vec<f64>,
    }

    extern "Rust" {
        /// A measured material (`fluo_matrix`, `fluo_gmm`): the diagonal (reflectance)
        /// plus reradiation, diffuse in direction.
        type MeasuredModel;

        /// `fluo_matrix`: a reradiation matrix file (.bfc, .csv, .exr), tabulated.
        fn matrix_new(filename: &str) -> Result<Box<MeasuredModel>>;
        /// `fluo_gmm`: a Gaussian-mixture fit file (.gmm.json, written by `fluo fit-gmm`).
        fn gmm_new(filename: &str) -> Result<Box<MeasuredModel>>;
        fn measured_is_fluorescent(model: &MeasuredModel) -> bool;
        /// out[j] = ρ(λ_j), the diagonal (elastic albedo).
        fn measured_elastic_albedo(model: &MeasuredModel, lambdas: &[f32], out: &mut [f32]);
        /// RGB variant: sRGB of ρ(λ) + ∫ P(λi, λ) dλi under equal-energy light (360–830 nm),
        /// bounded to [0, 1] per channel (`fluo::colour::bounded_rgb_albedo`).
        fn measured_rgb_albedo(model: &MeasuredModel) -> Rgb;
        /// RGB variant: sRGB of the diagonal ρ(λ) alone (the elastic part).
        fn measured_rgb_elastic(model: &MeasuredModel) -> Rgb;
        fn measured_to_string(model: &MeasuredModel) -> String;
        /// The model's fluorescent part, for the integrator.
        fn measured_fluorescence(model: &MeasuredModel) -> &Fluorescence;
        /// Check every value of a material-index texture selecting among `count` files
        /// (`fluo::models::check_material_index`; `width` as for `jung_check_values`).
        fn measured_check_index(values: &[f32], width: usize, count: usize) -> Result<()>;
        /// The longest wavelength it re-emits at (0 if it never does), to pick a
        /// representative among several materials.
        fn measured_emission_max(model: &MeasuredModel) -> f64;
        /// The tables the vectorised variants evaluate (see `MeasuredTables`).
        fn measured_tables(model: &MeasuredModel) -> MeasuredTables;
        /// `fluo_gmm` after an update through `mi.traverse`: the same fit with these
        /// component weights (renormalised to sum 1) and means (λi, λo), validated as a
        /// fit file is.
        fn gmm_updated(
            model: &MeasuredModel,
            weights: &[f64],
            means_excitation: &[f64],
            means_emission: &[f64],
        ) -> Result<Box<MeasuredModel>>;
    }

    // ------------------------------------------- fluo_path: generic handle, reduced RGB

    extern "Rust" {
        /// Any fluorescent model, seen through the bispectral interface
        /// (`core/src/interface.rs`) that the `fluo_path` integrator uses.
        type Fluorescence;

        /// Excitation wavelengths at which the model re-emits (empty if never).
        fn fluo_excitation_range(f: &Fluorescence) -> Range;
        /// Wavelengths at which it re-emits (empty if never).
        fn fluo_emission_range(f: &Fluorescence) -> Range;
        /// f_fl(λi, ωi, ωo, λo)·cos θo, sr⁻¹ nm⁻¹.
        fn fluo_reradiation(f: &Fluorescence, wi: &Vec3, wo: &Vec3, lambda_i: f64, lambda_o: f64) -> f64;
        /// ∫_range ∫ f_fl cos θo dωo dλi (chooses elastic vs shifted events).
        fn fluo_shift_albedo(f: &Fluorescence, wi: &Vec3, lambda_o: f64, range: &Range) -> f64;
        /// The shift albedo for one excitation range, tabulated over λo from
        /// `lambda_o_min` to Mitsuba's 830 nm when the model allows it (built once per
        /// scene; `fluo::shift` says why it stays unbiased).
        type ShiftTable;
        fn shift_table_new(f: &Fluorescence, range: &Range, lambda_o_min: f64) -> Box<ShiftTable>;
        /// [`fluo_shift_albedo`] for the table's range, through the table where it has one.
        fn shift_table_albedo(t: &ShiftTable, f: &Fluorescence, wi: &Vec3, lambda_o: f64) -> f64;
        /// λi given λo within `range` (camera paths).
        fn fluo_sample_excitation(f: &Fluorescence, wi: &Vec3, lambda_o: f64, xi: f64, range: &Range) -> Sample;

        /// Reduced (matrix-throughput) transport for scalar_rgb (core/src/reduce/).
        type TransportBasis;
        /// `basis`: rgb, xyzu or x7; `method`: ours or naive.
        fn transport_new(basis: &str, method: &str) -> Result<Box<TransportBasis>>;
        /// Number of transported channels K.
        fn transport_size(t: &TransportBasis) -> usize;
        /// 3×K row major: linear sRGB = output · c.
        fn transport_output(t: &TransportBasis, out: &mut [f64]);
        /// K×3 row major: coefficients of light given in linear sRGB.
        fn transport_from_rgb(t: &TransportBasis, out: &mut [f64]);
        /// K: coefficients of RGB white (1, 1, 1), to turn RGB albedos into per-band ones.
        fn transport_white(t: &TransportBasis, out: &mut [f64]);
        fn transport_name(t: &TransportBasis) -> &'static str;
        /// The basis and the reduction method ("x7/Ours"): two transports with the same
        /// label reduce a material alike (a key for caching reductions).
        fn transport_label(t: &TransportBasis) -> String;
        /// A fluorescent medium's operators reduced for a transport (`fluo_volpath` in
        /// scalar_rgb), K×K row major, 1/m at density 1: `absorption` A (the reduction of
        /// the diagonal μa(λ)) and `reradiation` F (of the density μa(λi) f(λi → λo)), so
        /// that light with coefficients c re-emits F·c/(4π) per unit length and steradian.
        fn medium_reduced(model: &FluoMedium, t: &TransportBasis, absorption: &mut [f64], reradiation: &mut [f64]);
        /// M = V·diag(λ)·V⁻¹ for a K×K row-major `m` with real, distinct, non-negative
        /// eigenvalues and well-conditioned V (`fluo::reduce::RealEigen`): a constant reduced
        /// medium's transfer exp(−M t) in closed form. False (nothing written) otherwise.
        fn reduced_eigen(m: &[f64], v: &mut [f64], v_inv: &mut [f64], lambda: &mut [f64]) -> bool;
        /// max of μa over the wavelengths reduced transport covers (its grid), 1/m: the
        /// RGB variants' majorant.
        fn medium_grid_absorption_max(model: &FluoMedium) -> f64;
        /// max over the grid of the fluorescent source μf (over the medium's whole
        /// range), 1/m: what the RGB majorant may have to cover for fluo_volpath.
        fn medium_grid_source_max(model: &FluoMedium) -> f64;

        /// A fluorescent model's reradiation reduced for a transport.
        type ReducedModel;
        fn reduced_new(f: &Fluorescence, t: &TransportBasis) -> Result<Box<ReducedModel>>;
        /// True when the matrix covers the elastic part too (its reflectance is known
        /// spectrally); otherwise the renderer adds the elastic part as a diagonal.
        fn reduced_includes_elastic(r: &ReducedModel) -> bool;
        /// K×K row major: the reduced reradiation times its directional factor (f·cos θo).
        fn reduced_reradiation(r: &ReducedModel, wi: &Vec3, wo: &Vec3, out: &mut [f64]);
        /// A Lambertian model's K×K matrix M (f = M/π): copied into `out` once, so that
        /// the integrator scales it by cos θo/π itself; false (nothing copied) for a
        /// direction-dependent model.
        fn reduced_lambertian(r: &ReducedModel, out: &mut [f64]) -> bool;
        /// The number of cosine nodes of a microfacet model's reduced operator (f·cos θo =
        /// D G/(4 cos θi)·M(cos θ), cos θ = ωi·h, M linear between the nodes j/(n − 1)).
        fn reduced_microfacet_nodes() -> usize;
        /// A microfacet model's node matrices as M_j = Σ_t w[j][t]·B_t
        /// (`fluo::reduce::LowRank`, at most `max_terms` terms, the fewest within
        /// [`REDUCED_LOW_RANK_TOLERANCE`] of the largest entry): B_t into `basis`
        /// (max_terms·K·K, zero beyond the terms) and w into `weights` ([nodes][max_terms]).
        /// Returns the truncation's relative error; negative for a Lambertian model.
        fn reduced_microfacet_low_rank(
            r: &ReducedModel,
            max_terms: usize,
            basis: &mut [f64],
            weights: &mut [f64],
        ) -> f64;
        /// [`REDUCED_LOW_RANK_TOLERANCE`].
        fn reduced_low_rank_tolerance() -> f64;
        /// Coefficients of an illuminant in a transport (K), Mitsuba's normalisation.
        fn illuminant_coefficients(s: &Illuminant, t: &TransportBasis, out: &mut [f64]);
        /// `fluo_jung` in the vectorised variants: its reduced operator split so that c
        /// and Q stay differentiable, M = `reflectance` − c·`absorbed` + c·Q·`reradiation`
        /// (each K×K row major, f = M/π; the reduction is linear in the operator). The
        /// first two are zero and `false` is returned when the reflectance is not given
        /// as sigmoid coefficients (the renderer adds its elastic part as a diagonal).
        fn jung_reduced_parts(
            model: &JungModel,
            t: &TransportBasis,
            reflectance: &mut [f64],
            absorbed: &mut [f64],
            reradiation: &mut [f64],
        ) -> bool;
    }
}

pub use bridge::{
    DyeMediumConfig, JungConfig, JungRgbParts, MeasuredTables, MediumJitTables, QdConfig, QdConstants, QdJitTables,
    QdMediumConfig, Range, Rgb, Sample, SampledSpectrum, Vec3,
};

// ---------------------------------------------------------------- shared value types

fn rgb(v: [f64; 3]) -> Rgb {
    Rgb { r: v[0], g: v[1], b: v[2] }
}

fn range_of(r: Option<(f64, f64)>) -> Range {
    r.map_or(Range { lo: 0.0, hi: 0.0 }, |(lo, hi)| Range { lo, hi })
}

fn sample_of(s: Option<(f64, f64)>) -> Sample {
    match s {
        Some((value, pdf)) if pdf > 0.0 && pdf.is_finite() && value.is_finite() => Sample { value, pdf },
        _ => Sample { value: 0.0, pdf: 0.0 },
    }
}

fn dir(v: &Vec3) -> [f64; 3] {
    [v.x, v.y, v.z]
}

fn copy_into(src: &[f64], out: &mut [f64]) {
    for (o, v) in out.iter_mut().zip(src) {
        *o = *v;
    }
}

/// Run a constructor, turning its error and any panic into the message of a C++
/// exception.
fn guarded<T>(f: impl FnOnce() -> fluo::Result<T>) -> Result<T, String> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(e.to_string()),
        Err(_) => Err("internal error (a panic was caught at the FFI boundary)".to_string()),
    }
}

// ------------------------------------------------------------------- fluo_illuminant

/// Opaque emission spectrum for `fluo_illuminant`.
pub struct Illuminant {
    label: String,
    spectrum: IrregularSpectrum,
}

fn illuminant_new(name: &str, filename: &str, scale: f64, normalize: bool) -> Result<Box<Illuminant>, String> {
    guarded(|| {
        let (label, spectrum) = match (name.is_empty(), filename.is_empty()) {
            (false, true) => (name.to_string(), IrregularSpectrum::from(illuminant(name)?)),
            (true, false) => (filename.to_string(), IrregularSpectrum::from_csv_file(filename)?),
            _ => {
                return Err(fluo::Error::param(
                    "illuminant",
                    format!("name \"{name}\", filename \"{filename}\""),
                    "exactly one of \"illuminant\" (a CIE name) and \"filename\" (a CSV spectrum)",
                ))
            }
        };
        if !(scale.is_finite() && scale >= 0.0) {
            return Err(fluo::Error::param("scale", scale, "[0, ∞)"));
        }
        fluo::spectrum::check_lamp(&label, spectrum.wavelengths_nm(), spectrum.values())?;
        let c = cmf(Observer::Cie1931);
        let y = c.y();
        let lum = spectrum.integrate_product(y, CIE_MIN_NM, CIE_MAX_NM, 1.0)?
            / y.integrate_product(&|_: f64| 1.0, CIE_MIN_NM, CIE_MAX_NM, 1.0)?;
        let k = if normalize {
            if !(lum > 0.0) {
                return Err(fluo::Error::data(format!(
                    "{label}: no visible energy (zero luminance), cannot normalise; set normalize = false"
                )));
            }
            scale / lum
        } else {
            scale
        };
        let scaled = IrregularSpectrum::new(
            spectrum.wavelengths_nm().to_vec(),
            spectrum.values().iter().map(|v| v * k).collect(),
        )?;
        fluo::spectrum::check_lamp(&format!("{label} × {}", fluo::num(k)), scaled.wavelengths_nm(), scaled.values())?;
        Ok(Box::new(Illuminant { label, spectrum: scaled }))
    })
}

fn illuminant_eval(s: &Illuminant, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = s.spectrum.eval(f64::from(l)) as f32;
    }
}

fn illuminant_nodes(s: &Illuminant, wavelengths: &mut Vec<f64>, values: &mut Vec<f64>) {
    wavelengths.clear();
    wavelengths.extend_from_slice(s.spectrum.wavelengths_nm());
    values.clear();
    values.extend_from_slice(s.spectrum.values());
}

fn illuminant_range(s: &Illuminant) -> Range {
    let w = s.spectrum.wavelengths_nm();
    Range { lo: w.first().copied().unwrap_or(0.0), hi: w.last().copied().unwrap_or(0.0) }
}

fn illuminant_mean(s: &Illuminant) -> f64 {
    s.spectrum.integrate_product(&|_: f64| 1.0, CIE_MIN_NM, CIE_MAX_NM, 1.0).unwrap_or(0.0) / (CIE_MAX_NM - CIE_MIN_NM)
}

fn illuminant_srgb(s: &Illuminant) -> Rgb {
    // Out-of-gamut (negative) channels clipped, as an sRGB film must store them: a violet
    // or UV lamp has negative linear-sRGB green, which Mitsuba reports per sample as an
    // invalid value.
    rgb(spectrum_to_srgb(|l| s.spectrum.eval(l)).map(|v| v.max(0.0)))
}

fn illuminant_to_string(s: &Illuminant) -> String {
    let r = illuminant_range(s);
    format!("{} ({}-{} nm)", s.label, r.lo, r.hi)
}

/// Wavelength below which light counts as ultraviolet for [`illuminant_is_mostly_uv`], nm.
const UV_EDGE_NM: f64 = 400.0;

fn illuminant_is_mostly_uv(s: &Illuminant) -> bool {
    let Range { lo, hi } = illuminant_range(s);
    let power = |a: f64, b: f64| {
        if b > a {
            s.spectrum.integrate_product(&|_: f64| 1.0, a, b, 1.0).unwrap_or(0.0)
        } else {
            0.0
        }
    };
    let total = power(lo, hi);
    total > 0.0 && power(lo, hi.min(UV_EDGE_NM)) > 0.5 * total
}

// ------------------------------------------------------------------------- fluo_jung

/// Opaque `fluo_jung` material handed to C++: the dye, shared with the generic handle,
/// whose `elastic` is the base reflectance when it is given as sigmoid coefficients.
pub struct JungModel {
    dye: Arc<JungFluorescence>,
    generic: Fluorescence,
}

impl JungModel {
    fn new(config: &JungConfig) -> fluo::Result<Self> {
        let dye = Arc::new(JungFluorescence::new(JungParams {
            emission_peak: config.emission_peak,
            stokes_shift: config.stokes_shift,
            concentration: config.concentration,
            quantum_yield: config.quantum_yield,
        })?);
        let reflectance = if config.has_coefficients {
            Some(Reflectance::Sigmoid(SigmoidPolynomial::new([config.c0, config.c1, config.c2])?))
        } else {
            None
        };
        Ok(JungModel { generic: Fluorescence { model: Model::Jung(Arc::clone(&dye)), elastic: reflectance }, dye })
    }

    /// The base reflectance r(λ) when given as coefficients, else 0.
    fn reflectance(&self, lambda: f64) -> f64 {
        self.generic.elastic.as_ref().map_or(0.0, |r| r.eval(lambda))
    }
}

fn jung_new(config: &JungConfig) -> Result<Box<JungModel>, String> {
    guarded(|| JungModel::new(config).map(Box::new))
}

fn jung_default_config() -> JungConfig {
    let p = JungParams::default();
    JungConfig {
        emission_peak: p.emission_peak,
        stokes_shift: p.stokes_shift,
        concentration: p.concentration,
        quantum_yield: p.quantum_yield,
        has_coefficients: false,
        c0: 0.0,
        c1: 0.0,
        c2: 0.0,
    }
}

fn jung_is_fluorescent(model: &JungModel) -> bool {
    model.dye.is_fluorescent()
}

fn jung_elastic_factor(model: &JungModel, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = model.dye.elastic_factor(f64::from(l)) as f32;
    }
}

fn jung_elastic_albedo(model: &JungModel, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        let l = f64::from(l);
        *o = (model.reflectance(l) * model.dye.elastic_factor(l)) as f32;
    }
}

fn jung_rgb_albedo(model: &JungModel) -> Rgb {
    rgb_bounded_albedo(jung_rgb_elastic(model), jung_rgb_fluorescence(model))
}

fn jung_rgb_elastic(model: &JungModel) -> Rgb {
    rgb(spectrum_to_srgb(|l| model.reflectance(l) * model.dye.elastic_factor(l)))
}

fn rgb_bounded_albedo(elastic: Rgb, reradiated: Rgb) -> Rgb {
    rgb(bounded_rgb_albedo([elastic.r, elastic.g, elastic.b], [reradiated.r, reradiated.g, reradiated.b]))
}

fn jung_rgb_elastic_scale(model: &JungModel) -> Rgb {
    let num = spectrum_to_srgb(|l| model.dye.elastic_factor(l));
    let den = spectrum_to_srgb(|_| 1.0);
    let ratio = |k: usize| if den[k].abs() > 0.0 { (num[k] / den[k]).clamp(0.0, 1.0) } else { 1.0 };
    rgb([ratio(0), ratio(1), ratio(2)])
}

fn jung_rgb_fluorescence(model: &JungModel) -> Rgb {
    // c·Q·∫_{360}^{830} a(λ) dλ: reradiated energy per unit equal-energy irradiance.
    let p = model.dye.params();
    let w = p.concentration * p.quantum_yield * model.dye.absorption_integral_range(CIE_MIN_NM, CIE_MAX_NM);
    if w <= 0.0 {
        return rgb([0.0; 3]);
    }
    rgb(spectrum_to_srgb(|l| w * model.dye.emission(l)))
}

fn jung_to_string(model: &JungModel) -> String {
    match &model.generic.elastic {
        Some(Reflectance::Sigmoid(s)) => format!("{} with sigmoid reflectance {:?}", model.dye, s.coefficients),
        _ => model.dye.to_string(),
    }
}

fn jung_fluorescence(model: &JungModel) -> &Fluorescence {
    &model.generic
}

/// Opaque coefficient cube handed to C++: shared by every material that loads the same
/// file (see [`shared_cube`]).
pub struct UpsampleCube(std::sync::Arc<fluo::upsample::Cube>);

/// Cubes loaded so far, by file and its modification time and length (a rewritten file
/// is loaded again); weak, so a cube no scene uses is freed.
type CubeKey = (std::path::PathBuf, Option<std::time::SystemTime>, u64);
static CUBES: std::sync::Mutex<Vec<(CubeKey, std::sync::Weak<fluo::upsample::Cube>)>> =
    std::sync::Mutex::new(Vec::new());

/// The cube in `path`, loaded once per file and shared: a scene with many coloured
/// materials holds one copy (1.6 MB for a shipped cube) and reads it once.
fn shared_cube(path: &std::path::Path) -> fluo::Result<std::sync::Arc<fluo::upsample::Cube>> {
    let meta = std::fs::metadata(path).ok();
    let key: CubeKey = (
        std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf()),
        meta.as_ref().and_then(|m| m.modified().ok()),
        meta.as_ref().map_or(0, |m| m.len()),
    );
    let mut cache = CUBES.lock().unwrap_or_else(|e| e.into_inner());
    cache.retain(|(_, weak)| weak.strong_count() > 0);
    if let Some(cube) = cache.iter().find(|(k, _)| *k == key).and_then(|(_, weak)| weak.upgrade()) {
        return Ok(cube);
    }
    let cube = std::sync::Arc::new(fluo::upsample::Cube::load(path)?);
    cache.push((key, std::sync::Arc::downgrade(&cube)));
    Ok(cube)
}

fn upsample_cube_load(space: &str, filename: &str) -> Result<Box<UpsampleCube>, String> {
    guarded(|| {
        let space = fluo::colour::RgbSpace::from_name(space).map_err(|_| {
            fluo::Error::param("color_space", format!("\"{space}\""), "one of \"srgb\", \"rec2020\", \"acescg\"")
        })?;
        let path = if filename.is_empty() {
            fluo::upsample::shipped_cube_dir().join(format!("{}_d65_tinf_r33.cube", fluo::upsample::space_name(space)))
        } else {
            std::path::PathBuf::from(filename)
        };
        let cube = shared_cube(&path)?;
        if cube.header.space != space {
            return Err(fluo::Error::param(
                "cube",
                format!("\"{}\" (a {} cube)", path.display(), fluo::upsample::space_name(cube.header.space)),
                format!("a cube generated for color_space \"{}\"", fluo::upsample::space_name(space)),
            ));
        }
        Ok(Box::new(UpsampleCube(cube)))
    })
}

fn upsample_cube_describe(cube: &UpsampleCube) -> String {
    cube.0.header.to_string()
}

/// The `fluo_jung` configuration of one colour's cube coefficients.
fn jung_config_of(c: &fluo::upsample::Coefficients) -> JungConfig {
    JungConfig {
        emission_peak: c.emission_peak,
        stokes_shift: c.stokes_shift,
        concentration: c.concentration,
        quantum_yield: fluo::upsample::QUANTUM_YIELD,
        has_coefficients: true,
        c0: c.reflectance[0],
        c1: c.reflectance[1],
        c2: c.reflectance[2],
    }
}

fn upsample_lookup(cube: &UpsampleCube, rgb: &[f64], lookup: &str, fluorescence: bool) -> Result<JungConfig, String> {
    guarded(|| {
        let mode = fluo::upsample::Lookup::from_name(lookup)?;
        let [r, g, b] = <[f64; 3]>::try_from(rgb)
            .map_err(|_| fluo::Error::param("color", format!("{} values", rgb.len()), "3 values (r, g, b)"))?;
        Ok(jung_config_of(&cube.0.lookup([r, g, b], mode, fluorescence)?))
    })
}

/// Opaque per-texel models of a `fluo_jung` colour texture.
pub struct JungTexture {
    width: usize,
    height: usize,
    /// Index into `models` per texel, row-major from the top row.
    texel: Vec<u32>,
    models: Vec<JungModel>,
    /// sRGB albedo per model (RGB variant).
    rgb: Vec<Rgb>,
    representative: usize,
}

fn jung_texture_new(
    cube: &UpsampleCube,
    width: usize,
    height: usize,
    rgb: &[f32],
    lookup: &str,
    fluorescence: bool,
) -> Result<Box<JungTexture>, String> {
    guarded(|| {
        let mode = fluo::upsample::Lookup::from_name(lookup)?;
        if width == 0 || height == 0 || rgb.len() != width * height * 3 {
            return Err(fluo::Error::data(format!(
                "color texture: {} values for {width} x {height} texels (expected {})",
                rgb.len(),
                width * height * 3
            )));
        }
        let mut index: std::collections::HashMap<[u64; 6], u32> = std::collections::HashMap::new();
        let mut models = Vec::new();
        let mut texel = Vec::with_capacity(width * height);
        for (t, px) in rgb.chunks_exact(3).enumerate() {
            let v = [f64::from(px[0]), f64::from(px[1]), f64::from(px[2])];
            let c = cube.0.lookup(v, mode, fluorescence).map_err(|_| {
                fluo::Error::param(
                    "color",
                    format!("texel (x = {}, y = {}) = ({}, {}, {})", t % width, t / width, v[0], v[1], v[2]),
                    "finite values in [0, 1] per component (the coefficient cube spans the unit RGB cube)",
                )
            })?;
            let key = [
                c.reflectance[0].to_bits(),
                c.reflectance[1].to_bits(),
                c.reflectance[2].to_bits(),
                c.emission_peak.to_bits(),
                c.concentration.to_bits(),
                c.stokes_shift.to_bits(),
            ];
            let id = match index.get(&key) {
                Some(&id) => id,
                None => {
                    let id = models.len() as u32;
                    models.push(JungModel::new(&jung_config_of(&c))?);
                    index.insert(key, id);
                    id
                }
            };
            texel.push(id);
        }
        let rgb = models.iter().map(jung_rgb_albedo).collect();
        let representative = models
            .iter()
            .enumerate()
            .filter(|(_, m)| m.dye.is_fluorescent())
            .max_by(|a, b| a.1.dye.emission_support().1.total_cmp(&b.1.dye.emission_support().1))
            .map_or(0, |(i, _)| i);
        Ok(Box::new(JungTexture { width, height, texel, models, rgb, representative }))
    })
}

fn texel_index(tex: &JungTexture, x: i64, y: i64) -> usize {
    let (w, h) = (tex.width as i64, tex.height as i64);
    let (x, y) = (x.rem_euclid(w), y.rem_euclid(h));
    tex.texel.get((y * w + x) as usize).map_or(0, |&i| i as usize)
}

fn jung_texture_model(tex: &JungTexture, x: i64, y: i64) -> &JungModel {
    &tex.models[texel_index(tex, x, y).min(tex.models.len() - 1)]
}

fn jung_texture_rgb(tex: &JungTexture, x: i64, y: i64) -> Rgb {
    let i = texel_index(tex, x, y).min(tex.rgb.len() - 1);
    let c = &tex.rgb[i];
    Rgb { r: c.r, g: c.g, b: c.b }
}

fn jung_texture_representative(tex: &JungTexture) -> &JungModel {
    &tex.models[tex.representative]
}

fn jung_config(model: &JungModel) -> JungConfig {
    let p = model.dye.params();
    let coefficients = match &model.generic.elastic {
        Some(Reflectance::Sigmoid(s)) => Some(s.coefficients),
        _ => None,
    };
    let [c0, c1, c2] = coefficients.unwrap_or([0.0; 3]);
    JungConfig {
        emission_peak: p.emission_peak,
        stokes_shift: p.stokes_shift,
        concentration: p.concentration,
        quantum_yield: p.quantum_yield,
        has_coefficients: coefficients.is_some(),
        c0,
        c1,
        c2,
    }
}

fn jung_texture_is_fluorescent(tex: &JungTexture) -> bool {
    tex.models.iter().any(|m| m.dye.is_fluorescent())
}

fn jung_texture_distinct(tex: &JungTexture) -> usize {
    tex.models.len()
}

fn jung_check_values(name: &str, values: &[f32], width: usize) -> Result<(), String> {
    check_texture_values(name, values, width, fluo::models::jung::check_param_value)
}

/// Check each value of a parameter texture with `check`, naming the first failing one by
/// its texel (`width` > 0) or its position.
fn check_texture_values(
    name: &str,
    values: &[f32],
    width: usize,
    check: impl Fn(&str, f64) -> fluo::Result<()>,
) -> Result<(), String> {
    guarded(|| {
        for (i, &v) in values.iter().enumerate() {
            if let Err(e) = check(name, f64::from(v)) {
                let at = if width > 0 {
                    format!("at texel (x = {}, y = {}) of its texture", i % width, i / width)
                } else {
                    format!("(value {i} of its texture)")
                };
                return Err(match e {
                    fluo::Error::InvalidParameter { name, value, valid } => {
                        fluo::Error::InvalidParameter { name, value: format!("{value} {at}"), valid }
                    }
                    other => other,
                });
            }
        }
        Ok(())
    })
}

fn jung_absorption(model: &JungModel, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = model.dye.absorption(f64::from(l)) as f32;
    }
}

fn jung_reflectance(model: &JungModel, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = model.reflectance(f64::from(l)) as f32;
    }
}

fn jung_rgb_parts(dye: &JungModel, base: &JungModel) -> JungRgbParts {
    let a = spectrum_to_srgb(|l| dye.dye.absorption(l));
    let white = spectrum_to_srgb(|_| 1.0);
    let ratio = |k: usize| if white[k].abs() > 0.0 { a[k] / white[k] } else { 0.0 };
    let unit = dye.dye.absorption_integral_range(CIE_MIN_NM, CIE_MAX_NM);
    JungRgbParts {
        reflectance: rgb(spectrum_to_srgb(|l| base.reflectance(l))),
        reflectance_absorbed: rgb(spectrum_to_srgb(|l| base.reflectance(l) * dye.dye.absorption(l))),
        absorbed_scale: rgb([ratio(0), ratio(1), ratio(2)]),
        fluorescence: rgb(spectrum_to_srgb(|l| unit * dye.dye.emission(l))),
    }
}

/// Most (λe, s) pairs a textured `fluo_jung` may combine (about 1 kB each).
const MAX_JUNG_SHAPES: usize = 4096;

/// Opaque dye shapes of a `fluo_jung` with textured parameters.
pub struct JungShapes {
    models: Vec<JungModel>,
    representative: usize,
}

fn jung_shapes_new(peaks: &[f64], shifts: &[f64]) -> Result<Box<JungShapes>, String> {
    guarded(|| {
        let n = peaks.len().saturating_mul(shifts.len());
        if n == 0 || n > MAX_JUNG_SHAPES {
            return Err(fluo::Error::data(format!(
                "textured emission_peak and stokes_shift: {} distinct peaks × {} distinct shifts = {n} dye \
                 shapes (at least 1, at most {MAX_JUNG_SHAPES}: quantize the textures to fewer values)",
                peaks.len(),
                shifts.len()
            )));
        }
        let mut models = Vec::with_capacity(n);
        for &emission_peak in peaks {
            for &stokes_shift in shifts {
                let config = JungConfig {
                    emission_peak,
                    stokes_shift,
                    concentration: 1.0,
                    quantum_yield: 1.0,
                    ..jung_default_config()
                };
                models.push(JungModel::new(&config).map_err(|e| match e {
                    fluo::Error::InvalidParameter { name, value, valid } if peaks.len() > 1 || shifts.len() > 1 => {
                        fluo::Error::InvalidParameter {
                            name,
                            value: format!(
                                "{value} (the pair emission_peak = {}, stokes_shift = {} of the textures' values)",
                                fluo::num(emission_peak),
                                fluo::num(stokes_shift)
                            ),
                            valid,
                        }
                    }
                    other => other,
                })?);
            }
        }
        let representative = models
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.dye.emission_support().1.total_cmp(&b.1.dye.emission_support().1))
            .map_or(0, |(i, _)| i);
        Ok(Box::new(JungShapes { models, representative }))
    })
}

fn jung_shapes_len(shapes: &JungShapes) -> usize {
    shapes.models.len()
}

fn jung_shapes_model(shapes: &JungShapes, i: usize) -> &JungModel {
    &shapes.models[i.min(shapes.models.len() - 1)]
}

fn jung_shapes_representative(shapes: &JungShapes) -> usize {
    shapes.representative
}

// --------------------------------------------------------------------------- fluo_qd

/// Opaque `fluo_qd` material handed to C++: the coating, shared with the generic handle.
pub struct QdModel {
    coating: Arc<qd::QdModel>,
    generic: Fluorescence,
}

/// `From` both ways between a bridge struct and its core twin with the same fields,
/// each field named once.
macro_rules! mirror {
    ($bridge:ty, $core:ty { $($field:ident),* $(,)? }) => {
        impl From<&$core> for $bridge {
            fn from(c: &$core) -> Self {
                Self { $($field: c.$field),* }
            }
        }
        impl From<&$bridge> for $core {
            fn from(b: &$bridge) -> Self {
                Self { $($field: b.$field),* }
            }
        }
    };
}

mirror!(
    QdConstants,
    qd::QdConstants {
        gap_energy,
        elementary_charge,
        planck,
        light_speed,
        boltzmann,
        electron_mass,
        hole_mass,
        vacuum_permittivity,
        relative_permittivity,
        temperature,
    }
);

impl From<&QdConfig> for qd::QdParams {
    fn from(c: &QdConfig) -> Self {
        qd::QdParams {
            radius_nm: c.radius,
            width_nm: c.width,
            quantum_yield: c.quantum_yield,
            density: c.density,
            ext_ior: c.ext_ior,
            lambda_min_nm: c.lambda_min,
            lambda_max_nm: c.lambda_max,
            distribution: if c.ggx { qd::Distribution::Ggx } else { qd::Distribution::Beckmann },
            alpha: c.alpha,
            constants: (&c.constants).into(),
            cos_nodes: c.table_cos_nodes,
            table_step_nm: c.table_step,
        }
    }
}

impl From<&qd::QdParams> for QdConfig {
    fn from(p: &qd::QdParams) -> Self {
        QdConfig {
            radius: p.radius_nm,
            width: p.width_nm,
            quantum_yield: p.quantum_yield,
            density: p.density,
            ext_ior: p.ext_ior,
            lambda_min: p.lambda_min_nm,
            lambda_max: p.lambda_max_nm,
            ggx: p.distribution == qd::Distribution::Ggx,
            alpha: p.alpha,
            constants: (&p.constants).into(),
            table_cos_nodes: p.cos_nodes,
            table_step: p.table_step_nm,
        }
    }
}

/// A spectrum from shim samples: one value is a constant, several a table.
fn spectrum_of(name: &str, s: &SampledSpectrum) -> fluo::Result<IrregularSpectrum> {
    match s.values {
        [v] => IrregularSpectrum::new(vec![0.0, 1e4], vec![*v, *v]),
        _ => IrregularSpectrum::new(s.wavelengths.to_vec(), s.values.to_vec())
            .map_err(|e| fluo::Error::data(format!("{name}: {e}"))),
    }
}

fn qd_new(
    config: &QdConfig,
    eta: &SampledSpectrum,
    k: &SampledSpectrum,
    qd_eta: &SampledSpectrum,
    qd_k: &SampledSpectrum,
) -> Result<Box<QdModel>, String> {
    guarded(|| {
        let substrate = match (eta.values, k.values) {
            ([eta], [k]) => qd::Substrate::Constant { eta: *eta, k: *k },
            _ => qd::Substrate::Tabulated { eta: spectrum_of("eta", eta)?, k: spectrum_of("k", k)? },
        };
        let index = if qd_eta.values.is_empty() && qd_k.values.is_empty() {
            qd::QdIndex::CdSe
        } else {
            qd::QdIndex::Tabulated { n: spectrum_of("qd_eta", qd_eta)?, k: spectrum_of("qd_k", qd_k)? }
        };
        let coating = Arc::new(qd::QdModel::new(config.into(), index, substrate)?);
        // The coating's elastic reflectance R_tot(θ, λ) lives in the Rust model (the
        // substrate's eta/k are passed in), so reductions cover the whole operator.
        let generic =
            Fluorescence { model: Model::Qd(Arc::clone(&coating)), elastic: Some(Reflectance::Constant(1.0)) };
        Ok(Box::new(QdModel { coating, generic }))
    })
}

fn qd_default_config() -> QdConfig {
    (&qd::QdParams::default()).into()
}

fn qd_is_fluorescent(model: &QdModel) -> bool {
    model.coating.is_fluorescent()
}

fn qd_elastic_coefficients(model: &QdModel, cos_theta: f32, lambdas: &[f32], r_spe: &mut [f32], pass: &mut [f32]) {
    for ((&l, r), p) in lambdas.iter().zip(r_spe.iter_mut()).zip(pass.iter_mut()) {
        let c = model.coating.coating(f64::from(cos_theta), f64::from(l));
        let t = c.t_spe * (1.0 - c.a_tf);
        *r = c.r_spe as f32;
        *p = (t * t) as f32;
    }
}

fn qd_jit_tables(model: &QdModel, rows: usize, lambda: &[f64], extra_nm: &[f64]) -> QdJitTables {
    let m = &model.coating;
    let t = if lambda.is_empty() { m.jit_tables(rows, extra_nm) } else { m.jit_tables_on(rows, lambda, extra_nm) };
    let p = m.params();
    let (excitation_lo, excitation_hi) = t.excitation.unwrap_or((0.0, 0.0));
    QdJitTables {
        lambda: t.lambda,
        rows: t.rows,
        a_tot: t.a_tot,
        cdf: t.cdf,
        r_spe: t.r_spe,
        pass: t.pass,
        r_tot: t.r_tot,
        extra_r_spe: t.extra_r_spe,
        extra_pass: t.extra_pass,
        emission_peak_nm: t.emission_peak_nm,
        emission_scale_nm: t.emission_scale_nm,
        emission_norm: t.emission_norm,
        lambda_min: p.lambda_min_nm,
        lambda_max: p.lambda_max_nm,
        excitation_lo,
        excitation_hi,
    }
}

fn qd_to_string(model: &QdModel) -> String {
    model.coating.to_string()
}

fn qd_fluorescence(model: &QdModel) -> &Fluorescence {
    &model.generic
}

fn qd_check_values(name: &str, values: &[f32], width: usize) -> Result<(), String> {
    check_texture_values(name, values, width, qd::check_param_value)
}

fn qd_texture_grid_nodes() -> usize {
    qd::TEXTURE_GRID_NODES
}

fn qd_texture_max_radii() -> usize {
    qd::TEXTURE_MAX_RADII
}

fn qd_texture_max_alphas() -> usize {
    qd::TEXTURE_MAX_ALPHAS
}

// ------------------------------------------------ fluo_qd_medium, fluo_dye_medium

/// Opaque fluorescent medium handed to C++ (either plugin).
pub struct FluoMedium {
    model: MediumModel,
}

impl From<&QdMediumConfig> for qd::QdMediumParams {
    fn from(c: &QdMediumConfig) -> Self {
        qd::QdMediumParams {
            radius_nm: c.radius,
            width_nm: c.width,
            quantum_yield: c.quantum_yield,
            concentration_um: c.concentration,
            ext_ior: c.ext_ior,
            lambda_min_nm: c.lambda_min,
            lambda_max_nm: c.lambda_max,
            constants: (&c.constants).into(),
            table_step_nm: c.table_step,
        }
    }
}

fn qd_medium_new(config: &QdMediumConfig) -> Result<Box<FluoMedium>, String> {
    guarded(|| Ok(Box::new(FluoMedium { model: MediumModel::Qd(Box::new(qd::QdMedium::new(config.into())?)) })))
}

fn qd_medium_default_config() -> QdMediumConfig {
    let p = qd::QdMediumParams::default();
    QdMediumConfig {
        radius: p.radius_nm,
        width: p.width_nm,
        quantum_yield: p.quantum_yield,
        concentration: p.concentration_um,
        ext_ior: p.ext_ior,
        lambda_min: p.lambda_min_nm,
        lambda_max: p.lambda_max_nm,
        constants: (&p.constants).into(),
        table_step: p.table_step_nm,
    }
}

fn dye_medium_new(c: &DyeMediumConfig) -> Result<Box<FluoMedium>, String> {
    guarded(|| {
        let p = DyeMediumParams {
            emission_peak_nm: c.emission_peak,
            stokes_shift_nm: c.stokes_shift,
            quantum_yield: c.quantum_yield,
            sigma_a_per_m: c.sigma_a,
        };
        Ok(Box::new(FluoMedium { model: MediumModel::Dye(DyeMedium::new(p)?) }))
    })
}

fn dye_medium_default_config() -> DyeMediumConfig {
    let p = DyeMediumParams::default();
    DyeMediumConfig {
        emission_peak: p.emission_peak_nm,
        stokes_shift: p.stokes_shift_nm,
        quantum_yield: p.quantum_yield,
        sigma_a: p.sigma_a_per_m,
    }
}

fn medium_is_fluorescent(model: &FluoMedium) -> bool {
    model.model.is_fluorescent()
}

fn medium_absorption(model: &FluoMedium, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = model.model.absorption_per_m(f64::from(l)) as f32;
    }
}

fn medium_absorption_rgb(model: &FluoMedium) -> Rgb {
    let c = spectrum_to_srgb(|l| model.model.absorption_per_m(l));
    rgb([c[0].max(0.0), c[1].max(0.0), c[2].max(0.0)])
}

fn medium_lambda_range(model: &FluoMedium) -> Range {
    range_of(Some(model.model.lambda_range()))
}

fn medium_shift_coefficients(model: &FluoMedium, lambdas: &[f32], range: &Range, out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = model.model.shift_coefficient_per_m(f64::from(l), (range.lo, range.hi)) as f32;
    }
}

fn medium_shift_and_sample(
    model: &FluoMedium,
    lambdas: &[f32],
    xis: &[f64],
    range: &Range,
    mu_f: &mut [f32],
    samples: &mut [Sample],
) {
    for (((l, xi), m), s) in lambdas.iter().zip(xis).zip(mu_f.iter_mut()).zip(samples.iter_mut()) {
        let (f, sample) = model.model.shift_and_sample(f64::from(*l), (range.lo, range.hi), *xi);
        *m = f as f32;
        *s = sample_of(sample);
    }
}

fn medium_jit_tables(model: &FluoMedium) -> MediumJitTables {
    let t = model.model.jit_tables();
    MediumJitTables {
        lambda: t.lambda,
        mu_a: t.mu_a,
        cum: t.cum,
        emission_lambda: t.emission_lambda,
        emission: t.emission,
    }
}

fn medium_to_string(model: &FluoMedium) -> String {
    model.model.to_string()
}

// --------------------------------------------------------- fluo_matrix, fluo_gmm

/// Opaque measured material (`fluo_matrix`, `fluo_gmm`) handed to C++: everything it
/// serves goes through the bispectral interface, so the generic handle is its only
/// field, with the measured diagonal as the model's elastic albedo.
pub struct MeasuredModel(Fluorescence);

impl MeasuredModel {
    fn new(model: Model) -> Box<Self> {
        Box::new(MeasuredModel(Fluorescence { model, elastic: Some(Reflectance::Constant(1.0)) }))
    }

    fn elastic_albedo(&self, lambda: f64) -> f64 {
        self.0.model.elastic_albedo(1.0, lambda)
    }
}

fn matrix_new(filename: &str) -> Result<Box<MeasuredModel>, String> {
    guarded(|| Ok(MeasuredModel::new(Model::Matrix(Arc::new(fluo::models::matrix::MatrixModel::from_file(filename)?)))))
}

fn gmm_new(filename: &str) -> Result<Box<MeasuredModel>, String> {
    guarded(|| Ok(MeasuredModel::new(Model::Gmm(Arc::new(fluo::models::gmm::GmmModel::from_file(filename)?)))))
}

fn measured_is_fluorescent(model: &MeasuredModel) -> bool {
    model.0.model.excitation_range().is_some()
}

fn measured_elastic_albedo(model: &MeasuredModel, lambdas: &[f32], out: &mut [f32]) {
    for (o, &l) in out.iter_mut().zip(lambdas) {
        *o = model.elastic_albedo(f64::from(l)) as f32;
    }
}

fn measured_rgb_albedo(model: &MeasuredModel) -> Rgb {
    const UP: [f64; 3] = [0.0, 0.0, 1.0];
    let shifted = |l: f64| model.0.model.shift_albedo(UP, l, (CIE_MIN_NM, CIE_MAX_NM));
    rgb(bounded_rgb_albedo(spectrum_to_srgb(|l| model.elastic_albedo(l)), spectrum_to_srgb(shifted)))
}

fn measured_rgb_elastic(model: &MeasuredModel) -> Rgb {
    rgb(spectrum_to_srgb(|l| model.elastic_albedo(l)))
}

fn measured_to_string(model: &MeasuredModel) -> String {
    model.0.model.to_string()
}

fn measured_check_index(values: &[f32], width: usize, count: usize) -> Result<(), String> {
    check_texture_values("index", values, width, |_, v| fluo::models::check_material_index(v, count))
}

fn measured_emission_max(model: &MeasuredModel) -> f64 {
    fluo::Bispectral::emission_range(&model.0.model).map_or(0.0, |r| r.1)
}

fn measured_tables(model: &MeasuredModel) -> MeasuredTables {
    let mut t = MeasuredTables {
        kind: String::new(),
        diagonal_nm: Vec::new(),
        diagonal: Vec::new(),
        lambda_i: Vec::new(),
        lambda_o: Vec::new(),
        p: Vec::new(),
        row_cdf: Vec::new(),
        scale: 0.0,
        rect: Vec::new(),
        components: Vec::new(),
    };
    match &model.0.model {
        Model::Matrix(m) => {
            let (nm, d) = m.diagonal();
            let (p, row_cdf) = m.row_tables();
            t = MeasuredTables {
                kind: "matrix".into(),
                diagonal_nm: nm.to_vec(),
                diagonal: d.to_vec(),
                lambda_i: m.lambda_i().to_vec(),
                lambda_o: m.lambda_o().to_vec(),
                p: p.to_vec(),
                row_cdf: row_cdf.to_vec(),
                ..t
            };
        }
        Model::Gmm(g) => {
            let f = g.file();
            t.kind = "gmm".into();
            t.diagonal_nm.clone_from(&f.diagonal.wavelengths_nm);
            t.diagonal.clone_from(&f.diagonal.values);
            t.scale = f.scale;
            t.rect =
                vec![f.lambda_i_range_nm[0], f.lambda_i_range_nm[1], f.lambda_o_range_nm[0], f.lambda_o_range_nm[1]];
            for c in &f.components {
                let [[aa, ab], [ba, bb]] = c.covariance;
                t.components.extend([c.weight, c.mean[0], c.mean[1], aa, 0.5 * (ab + ba), bb]);
            }
        }
        _ => {}
    }
    t
}

fn gmm_updated(
    model: &MeasuredModel,
    weights: &[f64],
    means_excitation: &[f64],
    means_emission: &[f64],
) -> Result<Box<MeasuredModel>, String> {
    guarded(|| {
        let Model::Gmm(g) = &model.0.model else {
            return Err(fluo::Error::data("not a Gaussian-mixture material".to_string()));
        };
        let mut file = g.file().clone();
        let n = file.components.len();
        if weights.len() != n || means_excitation.len() != n || means_emission.len() != n {
            return Err(fluo::Error::param("weights", weights.len(), format!("{n} entries (one per component)")));
        }
        let total: f64 = weights.iter().sum();
        if let Some(w) = weights.iter().find(|w| !(w.is_finite() && **w >= 0.0)) {
            return Err(fluo::Error::param("weights", w, "[0, ∞) (renormalised to sum 1)"));
        }
        if !(total > 0.0 && total.is_finite()) {
            return Err(fluo::Error::param("weights", format!("sum {total}"), "a positive sum"));
        }
        for (k, c) in file.components.iter_mut().enumerate() {
            c.weight = weights[k] / total;
            c.mean = [means_excitation[k], means_emission[k]];
        }
        Ok(MeasuredModel::new(Model::Gmm(Arc::new(fluo::models::gmm::GmmModel::new(file)?))))
    })
}

fn measured_fluorescence(model: &MeasuredModel) -> &Fluorescence {
    &model.0
}

// ------------------------------------------- fluo_path: generic handle, reduced RGB

/// Opaque fluorescent model handed to C++ (see [`fluo::interface`]).
///
/// `elastic` is the elastic reflectance when Rust knows it spectrally (sigmoid
/// coefficients; measured diagonals), so that reductions can cover the whole operator
/// ρ(λ)·diag + P as in Fichet et al.; `None` when it comes from a Mitsuba texture.
pub struct Fluorescence {
    model: Model,
    elastic: Option<Reflectance>,
}

/// Opaque [`fluo::shift::ShiftTable`] (none for direction-dependent models) and its range.
pub struct ShiftTable {
    table: Option<fluo::shift::ShiftTable>,
    range: (f64, f64),
}

fn shift_table_new(f: &Fluorescence, range: &Range, lambda_o_min: f64) -> Box<ShiftTable> {
    let r = (range.lo, range.hi);
    let table = catch_unwind(AssertUnwindSafe(|| {
        fluo::shift::ShiftTable::new(&f.model, r, (lambda_o_min.min(CIE_MIN_NM), CIE_MAX_NM.max(range.hi)))
    }))
    .ok()
    .flatten();
    Box::new(ShiftTable { table, range: r })
}

fn shift_table_albedo(t: &ShiftTable, f: &Fluorescence, wi: &Vec3, lambda_o: f64) -> f64 {
    match &t.table {
        Some(table) => table.eval(&f.model, dir(wi), lambda_o),
        None => f.model.shift_albedo(dir(wi), lambda_o, t.range),
    }
}

fn fluo_excitation_range(f: &Fluorescence) -> Range {
    range_of(f.model.excitation_range())
}
fn fluo_emission_range(f: &Fluorescence) -> Range {
    range_of(f.model.emission_range())
}
fn fluo_reradiation(f: &Fluorescence, wi: &Vec3, wo: &Vec3, lambda_i: f64, lambda_o: f64) -> f64 {
    f.model.reradiation(dir(wi), dir(wo), lambda_i, lambda_o)
}
fn fluo_shift_albedo(f: &Fluorescence, wi: &Vec3, lambda_o: f64, range: &Range) -> f64 {
    f.model.shift_albedo(dir(wi), lambda_o, (range.lo, range.hi))
}
fn fluo_sample_excitation(f: &Fluorescence, wi: &Vec3, lambda_o: f64, xi: f64, range: &Range) -> Sample {
    sample_of(f.model.sample_excitation(dir(wi), lambda_o, xi, (range.lo, range.hi)))
}

/// Opaque reduced transport.
pub struct TransportBasis(Transport);

fn transport_new(basis: &str, method: &str) -> Result<Box<TransportBasis>, String> {
    guarded(|| Ok(Box::new(TransportBasis(Transport::new(basis, Method::from_name(method)?)?))))
}
fn transport_size(t: &TransportBasis) -> usize {
    t.0.len()
}
fn transport_output(t: &TransportBasis, out: &mut [f64]) {
    copy_into(&t.0.output, out);
}
fn transport_from_rgb(t: &TransportBasis, out: &mut [f64]) {
    copy_into(&t.0.from_rgb, out);
}
fn transport_white(t: &TransportBasis, out: &mut [f64]) {
    copy_into(&t.0.white, out);
}
fn transport_name(t: &TransportBasis) -> &'static str {
    t.0.name
}
fn transport_label(t: &TransportBasis) -> String {
    format!("{}/{:?}", t.0.name, t.0.method)
}

fn medium_grid_absorption_max(model: &FluoMedium) -> f64 {
    fluo::reduce::grid().into_iter().map(|l| model.model.absorption_per_m(l)).fold(0.0, f64::max)
}

fn medium_grid_source_max(model: &FluoMedium) -> f64 {
    let m = &model.model;
    let range = m.lambda_range();
    fluo::reduce::grid().into_iter().map(|l| m.shift_coefficient_per_m(l, range)).fold(0.0, f64::max)
}

fn reduced_eigen(m: &[f64], v: &mut [f64], v_inv: &mut [f64], lambda: &mut [f64]) -> bool {
    let k = lambda.len();
    if v.len() != k * k || v_inv.len() != k * k {
        return false;
    }
    match fluo::reduce::RealEigen::new(m, k) {
        Some(e) => {
            v.copy_from_slice(&e.v);
            v_inv.copy_from_slice(&e.v_inv);
            lambda.copy_from_slice(&e.lambda);
            true
        }
        None => false,
    }
}

fn medium_reduced(model: &FluoMedium, t: &TransportBasis, absorption: &mut [f64], reradiation: &mut [f64]) {
    let m = &model.model;
    copy_into(&t.0.reduce(&Operator::new(|l| m.absorption_per_m(l), |_, _| 0.0)), absorption);
    copy_into(
        &t.0.reduce(&Operator::new(|_| 0.0, |li, lo| m.absorption_per_m(li) * m.reradiation_per_nm(li, lo))),
        reradiation,
    );
}

/// Incidence-cosine nodes of angle-dependent reduced tables (uniform in cos θ,
/// linearly interpolated; the coating's own tables use the same kind of grid).
const REDUCED_COS_NODES: usize = 17;

/// Opaque reduced operator of one material, with its directional factor.
pub struct ReducedModel {
    directional: Directional,
    full: bool,
}

enum Directional {
    /// f = M/π (Lambertian): one K×K matrix.
    Lambertian(Vec<f64>),
    /// f = D G M(cos θ) / (4 cos θi cos θo), M tabulated at [`REDUCED_COS_NODES`]
    /// incidence cosines on the microfacet (cos θ = ωi·h).
    Microfacet { micro: qd::Microfacet, tables: Vec<Vec<f64>> },
}

fn reduced_new(f: &Fluorescence, t: &TransportBasis) -> Result<Box<ReducedModel>, String> {
    guarded(|| {
        Ok(Box::new(match (&f.model, &f.elastic) {
            (Model::Qd(m), _) => {
                let tables = (0..REDUCED_COS_NODES)
                    .map(|j| {
                        let c = j as f64 / (REDUCED_COS_NODES - 1) as f64;
                        t.0.reduce(&Operator::at(m.as_ref(), c.max(1e-3)).reradiation_only())
                    })
                    .collect();
                // Reradiation only: the plugin serves the elastic part per hit and per RGB
                // channel from the substrate's own eta/k (a gold substrate stays gold).
                ReducedModel { directional: Directional::Microfacet { micro: *m.microfacet(), tables }, full: false }
            }
            (_, Some(r)) => ReducedModel {
                directional: Directional::Lambertian(t.0.reduce(&Operator::new(
                    |l| r.eval(l) * f.model.elastic_albedo(1.0, l),
                    |li, lo| f.model.density(1.0, li, lo),
                ))),
                full: true,
            },
            (_, None) => ReducedModel {
                directional: Directional::Lambertian(t.0.reduce(&Operator::of(&f.model).reradiation_only())),
                full: false,
            },
        }))
    })
}

fn jung_reduced_parts(
    model: &JungModel,
    t: &TransportBasis,
    reflectance: &mut [f64],
    absorbed: &mut [f64],
    reradiation: &mut [f64],
) -> bool {
    let copy = |m: Vec<f64>, out: &mut [f64]| {
        for (o, v) in out.iter_mut().zip(m.iter().chain(std::iter::repeat(&0.0))) {
            *o = *v;
        }
    };
    let dye = &model.dye;
    copy(
        t.0.reduce(&Operator::new(
            |_| 0.0,
            |li, lo| {
                if lo > li {
                    dye.absorption(li) * dye.emission(lo)
                } else {
                    0.0
                }
            },
        )),
        reradiation,
    );
    let has_reflectance = model.generic.elastic.is_some();
    if has_reflectance {
        copy(t.0.reduce(&Operator::new(|l| model.reflectance(l), |_, _| 0.0)), reflectance);
        copy(t.0.reduce(&Operator::new(|l| model.reflectance(l) * dye.absorption(l), |_, _| 0.0)), absorbed);
    } else {
        reflectance.fill(0.0);
        absorbed.fill(0.0);
    }
    has_reflectance
}

fn reduced_includes_elastic(r: &ReducedModel) -> bool {
    r.full
}
fn reduced_lambertian(r: &ReducedModel, out: &mut [f64]) -> bool {
    match &r.directional {
        Directional::Lambertian(m) if out.len() == m.len() => {
            out.copy_from_slice(m);
            true
        }
        _ => false,
    }
}
fn reduced_microfacet_nodes() -> usize {
    REDUCED_COS_NODES
}
/// Relative error (of the largest entry) within which `reduced_microfacet_low_rank` looks
/// for the fewest terms; measured ≤ 8.7e-6 with at most 3 terms for coatings of radius
/// 1.5-4.5 nm, density 0.1-0.8, on gold, glass and a strong conductor, in every basis
/// (test `qd_reduced_operators_are_low_rank`). The vectorised `fluo_path` warns beyond it.
const REDUCED_LOW_RANK_TOLERANCE: f64 = 1e-5;
fn reduced_low_rank_tolerance() -> f64 {
    REDUCED_LOW_RANK_TOLERANCE
}
fn reduced_microfacet_low_rank(r: &ReducedModel, max_terms: usize, basis: &mut [f64], weights: &mut [f64]) -> f64 {
    let Directional::Microfacet { tables, .. } = &r.directional else { return -1.0 };
    let len = tables.first().map_or(0, Vec::len);
    if basis.len() != max_terms * len || weights.len() != tables.len() * max_terms {
        return f64::INFINITY;
    }
    let lr = fluo::reduce::LowRank::new(tables, max_terms, REDUCED_LOW_RANK_TOLERANCE);
    basis.iter_mut().for_each(|v| *v = 0.0);
    weights.iter_mut().for_each(|v| *v = 0.0);
    for (t, b) in lr.basis.iter().enumerate() {
        basis[t * len..(t + 1) * len].copy_from_slice(b);
    }
    for (j, w) in lr.weights.iter().enumerate() {
        weights[j * max_terms..j * max_terms + w.len()].copy_from_slice(w);
    }
    lr.error
}
fn reduced_reradiation(r: &ReducedModel, wi: &Vec3, wo: &Vec3, out: &mut [f64]) {
    match &r.directional {
        Directional::Lambertian(m) => {
            // f = M/π, times cos θo
            let factor = if wi.z > 0.0 && wo.z > 0.0 { wo.z * std::f64::consts::FRAC_1_PI } else { 0.0 };
            for (o, v) in out.iter_mut().zip(m) {
                *o = v * factor;
            }
        }
        Directional::Microfacet { micro, tables } => {
            // D G / (4 cos θi) M(cos θ), cos θ = ωi·h, M linear between nodes
            let Some((lobe, c)) = micro.lobe(dir(wi), dir(wo)) else {
                out.iter_mut().for_each(|o| *o = 0.0);
                return;
            };
            let x = c.clamp(0.0, 1.0) * (REDUCED_COS_NODES - 1) as f64;
            let j = (x.floor() as usize).min(REDUCED_COS_NODES - 2);
            let w = x - j as f64;
            if let (Some(a), Some(b)) = (tables.get(j), tables.get(j + 1)) {
                for ((o, va), vb) in out.iter_mut().zip(a).zip(b) {
                    *o = lobe * ((1.0 - w) * va + w * vb);
                }
            }
        }
    }
}
fn illuminant_coefficients(s: &Illuminant, t: &TransportBasis, out: &mut [f64]) {
    copy_into(&t.0.coefficients(&|l| s.spectrum.eval(l)), out);
}

/// Marks the plugin library: `import fluo` checks for it, so that `FLUO_LIBRARY` naming
/// another shared library fails with an explanation instead of "plugin not found".
#[no_mangle]
pub extern "C" fn fluo_plugins_built() -> u32 {
    1
}

/// The plugins registered so far, as `name:kind:variants` (`scalar` or `scalar,jit`; the
/// shims register themselves when the library is loaded).
static PLUGINS: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());
static PLUGIN_LIST: std::sync::OnceLock<std::ffi::CString> = std::sync::OnceLock::new();

fn note_plugin(name: &str, kind: &str, vectorised: bool) {
    if let Ok(mut list) = PLUGINS.lock() {
        list.push(format!("{name}:{kind}:{}", if vectorised { "scalar,jit" } else { "scalar" }));
    }
}

/// Every plugin the library registered, one `name:kind:variants` per line (read once, after
/// loading, by `fluo.PLUGINS`): the names are written once, in the shims.
#[no_mangle]
pub extern "C" fn fluo_plugin_list() -> *const std::ffi::c_char {
    PLUGIN_LIST
        .get_or_init(|| {
            let text = PLUGINS.lock().map(|l| l.join("\n")).unwrap_or_default();
            std::ffi::CString::new(text).unwrap_or_default()
        })
        .as_ptr()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> JungConfig {
        JungConfig { concentration: 0.0, has_coefficients: true, ..jung_default_config() }
    }

    #[test]
    fn errors_cross_as_messages() {
        let e = jung_new(&JungConfig { quantum_yield: 1.5, ..config() }).err().unwrap();
        assert!(e.contains("quantum_yield") && e.contains("1.5") && e.contains("[0, 1]"), "{e}");
        let e = jung_new(&JungConfig { c1: f64::NAN, ..config() }).err().unwrap();
        assert!(e.contains("coefficients[1]"), "{e}");
    }

    #[test]
    fn zero_concentration_is_plain_reflectance() {
        // coefficients (0,0,0) -> r = S(0) = 0.5 everywhere
        let m = jung_new(&config()).unwrap();
        let l = [300.0f32, 400.0, 555.0, 830.0];
        let mut out = [0.0f32; 4];
        jung_elastic_albedo(&m, &l, &mut out);
        assert_eq!(out, [0.5; 4]);
        let a = jung_rgb_albedo(&m);
        let white = spectrum_to_srgb(|_| 1.0);
        assert!((a.r - 0.5 * white[0]).abs() < 1e-12 && (a.b - 0.5 * white[2]).abs() < 1e-12);
        let f = jung_rgb_fluorescence(&m);
        assert_eq!((f.r, f.g, f.b), (0.0, 0.0, 0.0));
    }

    #[test]
    fn slices_of_different_length_do_not_panic() {
        let m = jung_new(&config()).unwrap();
        let mut out = [0.0f32; 2];
        jung_elastic_factor(&m, &[500.0, 510.0, 520.0], &mut out);
        jung_elastic_factor(&m, &[], &mut out);
    }

    #[test]
    fn jung_shares_one_model_with_its_generic_handle() {
        let m = jung_new(&JungConfig { concentration: 0.5, ..config() }).unwrap();
        assert_eq!(Arc::strong_count(&m.dye), 2);
        assert_eq!(jung_fluorescence(&m).model.name(), "jung");
    }

    fn spectrum<'a>(wavelengths: &'a [f64], values: &'a [f64]) -> SampledSpectrum<'a> {
        SampledSpectrum { wavelengths, values }
    }

    #[test]
    fn qd_config_round_trips_through_the_core_params() {
        let c = QdConfig { radius: 3.0, ggx: true, ..qd_default_config() };
        let back = QdConfig::from(&qd::QdParams::from(&c));
        assert!(back.radius == 3.0 && back.ggx && back.constants.temperature == c.constants.temperature);
    }

    #[test]
    fn qd_reduced_operators_are_low_rank() {
        // The vectorised fluo_path evaluates a coating's reduced reradiation as a few terms
        // w_t(cos θ)·B_t when the truncation is within REDUCED_LOW_RANK_TOLERANCE.
        let none = spectrum(&[], &[]);
        for (eta, k) in [(0.27, 2.9), (1.5, 0.0), (1.2, 7.0)] {
            for radius in [1.5, 2.2, 3.3, 4.5] {
                for density in [0.1, 0.8] {
                    let c = QdConfig { radius, density, ..qd_default_config() };
                    let m = qd_new(&c, &spectrum(&[0.0], &[eta]), &spectrum(&[0.0], &[k]), &none, &none).unwrap();
                    for basis in ["rgb", "xyzu", "x7"] {
                        let t = transport_new(basis, "ours").unwrap();
                        let r = reduced_new(qd_fluorescence(&m), &t).unwrap();
                        let kk = transport_size(&t).pow(2);
                        let (mut b, mut w) = (vec![0.0; 3 * kk], vec![0.0; 3 * REDUCED_COS_NODES]);
                        let e = reduced_microfacet_low_rank(&r, 3, &mut b, &mut w);
                        assert!(e <= REDUCED_LOW_RANK_TOLERANCE, "{e}");
                    }
                }
            }
        }
    }

    #[test]
    fn qd_errors_cross_as_messages_and_slices_are_safe() {
        let (eta, k, none) = (spectrum(&[0.0], &[1.5]), spectrum(&[0.0], &[0.0]), spectrum(&[], &[]));
        let e = qd_new(&QdConfig { density: 2.0, ..qd_default_config() }, &eta, &k, &none, &none).err().unwrap();
        assert!(e.contains("density") && e.contains("[0, 1]"), "{e}");
        let unsorted = spectrum(&[400.0, 300.0], &[1.0, 1.0]);
        let e = qd_new(&qd_default_config(), &unsorted, &unsorted, &none, &none).err().unwrap();
        assert!(e.contains("eta"), "{e}");
        let (qd_eta, qd_k) = (spectrum(&[400.0, 500.0], &[2.0, -1.0]), spectrum(&[400.0, 500.0], &[0.1, 0.1]));
        let e = qd_new(&qd_default_config(), &eta, &k, &qd_eta, &qd_k).err().unwrap();
        assert!(e.contains("qd_eta"), "{e}");
        let m = qd_new(&qd_default_config(), &eta, &k, &none, &none).unwrap();
        let (mut r, mut p) = ([0.0f32; 2], [0.0f32; 4]);
        qd_elastic_coefficients(&m, 0.5, &[400.0, 500.0, 600.0], &mut r, &mut p);
        assert!(r[0] >= 0.0 && p[0] > 0.0 && p[0] <= 1.0 && p[2] == 0.0);
        assert_eq!(qd_fluorescence(&m).model.name(), "qd");
        assert_eq!(Arc::strong_count(&m.coating), 2);
    }

    #[test]
    fn substrate_eta_and_k_keep_their_own_grids() {
        // k on a coarser grid than eta: Rust interpolates each on its own grid.
        let eta = spectrum(&[300.0, 500.0, 700.0, 900.0], &[1.5, 1.2, 0.9, 0.6]);
        let k = spectrum(&[300.0, 900.0], &[2.0, 8.0]);
        let none = spectrum(&[], &[]);
        let m = qd_new(&qd_default_config(), &eta, &k, &none, &none).unwrap();
        let (mut r, mut p) = ([0.0f32; 1], [0.0f32; 1]);
        qd_elastic_coefficients(&m, 0.8, &[600.0], &mut r, &mut p);
        assert!(r[0].is_finite() && p[0] > 0.0 && p[0] <= 1.0);
    }
}
