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
//! 1. shared value types ([`Rgb`], [`Range`]) and helpers;
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
use fluo::model::MediumModel;
use fluo::models::jung::{DyeMedium, DyeMediumParams, JungFluorescence, JungParams, Reflectance};
use fluo::models::qd;
use fluo::reduce::{Method, Operator, Transport};
use fluo::sigmoid::SigmoidPolynomial;
use fluo::spectrum::{cmf, illuminant, IrregularSpectrum, Observer, Spectral};
use fluo::Model;

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
        fn jung_to_string(model: &JungModel) -> String;
        /// The model's fluorescent part, for the integrator.
        fn jung_fluorescence(model: &JungModel) -> &Fluorescence;

        /// An RGB -> (reflectance + fluorescence) coefficient cube (`core/src/upsample/`).
        type UpsampleCube;

        /// Load the cube for `space` ("srgb", "rec2020", "acescg"): `filename`, or the
        /// shipped `data/cubes/<space>_d65_tinf_r33.cube` when empty. Errors for an
        /// unknown space, a malformed file, or a cube of another space.
        fn upsample_cube_load(space: &str, filename: &str) -> Result<Box<UpsampleCube>>;
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
        /// The tables of [`QdJitTables`] at `rows` cosines, with the coating's
        /// coefficients also at `extra_nm` (the RGB channels' wavelengths); `spectral`
        /// false: those alone (the λ tables left empty, `lambda` the model's grid).
        fn qd_jit_tables(model: &QdModel, rows: usize, lambda: &[f64], extra_nm: &[f64], spectral: bool)
            -> QdJitTables;
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
        /// RGB variants: μa as Mitsuba turns a spectrum into linear sRGB
        /// (`spectrum_to_srgb`), negative channels clipped to 0, 1/m.
        fn medium_absorption_rgb(model: &FluoMedium) -> Rgb;
        /// [λmin, λmax], nm: where absorption re-emits and where emission lands.
        fn medium_lambda_range(model: &FluoMedium) -> Range;
        fn medium_to_string(model: &FluoMedium) -> String;
        /// The tables of [`MediumJitTables`] (vectorised variants).
        fn medium_jit_tables(model: &FluoMedium) -> MediumJitTables;
        /// The same tables on given nodes (a parameter's derivative: differences of
        /// tables on one model's nodes).
        fn medium_jit_tables_on(model: &FluoMedium, lambda: &[f64], emission_lambda: &[f64]) -> MediumJitTables;
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
        /// `fluo_matrix` after an update through `mi.traverse`: the same matrix with the
        /// reradiation P at the nodes replaced (nm⁻¹, the layout of `MeasuredTables::p`),
        /// each entry finite and ≥ 0.
        fn matrix_updated(model: &MeasuredModel, reradiation: &[f64]) -> Result<Box<MeasuredModel>>;
        /// `fluo_matrix`: the reduced reradiation's derivative with respect to each node of
        /// P in transport `t` (`fluo::reduce::bilinear_jacobian`): one K×K matrix (row major)
        /// per node, in the layout of `MeasuredTables::p`.
        fn matrix_reduced_jacobian(model: &MeasuredModel, t: &TransportBasis) -> Result<Vec<f64>>;
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
        /// Reduced (matrix-throughput) transport for scalar_rgb (core/src/reduce/).
        type TransportBasis;
        /// `basis`: rgb, xyzu, x7 or auto (x7's bands until `transport_adaptive`); `method`:
        /// ours or naive.
        fn transport_new(basis: &str, method: &str) -> Result<Box<TransportBasis>>;
        /// The scene-adaptive transport (`auto`) for the scene's light spectra, `lights`
        /// their samples on the reduction grid one after the other (`illuminant_on_grid`).
        fn transport_adaptive(lights: &[f64], method: &str) -> Result<Box<TransportBasis>>;
        /// Number of transported channels K.
        fn transport_size(t: &TransportBasis) -> usize;
        /// 3×K row major: linear sRGB = output · c.
        fn transport_output(t: &TransportBasis, out: &mut [f64]);
        /// K×3 row major: coefficients of light given in linear sRGB.
        fn transport_from_rgb(t: &TransportBasis, out: &mut [f64]);
        /// K: coefficients of RGB white (1, 1, 1), to turn RGB albedos into per-band ones.
        fn transport_white(t: &TransportBasis, out: &mut [f64]);
        fn transport_name(t: &TransportBasis) -> &'static str;
        /// The basis and the reduction method ("x7/Ours"; `auto`'s with a digest of its light
        /// band): two transports with the same label reduce a material alike (a key for
        /// caching reductions).
        fn transport_label(t: &TransportBasis) -> String;
        /// A fluorescent medium's operators reduced for a transport (`fluo_volpath` in
        /// scalar_rgb), K×K row major, 1/m at density 1: `absorption` A (the reduction of
        /// the diagonal μa(λ)) and `reradiation` F (of the density μa(λi) f(λi → λo)), so
        /// that light with coefficients c re-emits F·c/(4π) per unit length and steradian.
        fn medium_reduced(model: &FluoMedium, t: &TransportBasis, absorption: &mut [f64], reradiation: &mut [f64]);
        /// max of μa over the wavelengths reduced transport covers (its grid), 1/m: the
        /// RGB variants' majorant.
        fn medium_grid_absorption_max(model: &FluoMedium) -> f64;

        /// A fluorescent model's reradiation reduced for a transport.
        type ReducedModel;
        fn reduced_new(f: &Fluorescence, t: &TransportBasis) -> Result<Box<ReducedModel>>;
        /// True when the matrix covers the elastic part too (its reflectance is known
        /// spectrally); otherwise the renderer adds the elastic part as a diagonal.
        fn reduced_includes_elastic(r: &ReducedModel) -> bool;
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
        /// Coefficients of an illuminant in a transport (K), Mitsuba's normalisation.
        fn illuminant_coefficients(s: &Illuminant, t: &TransportBasis, out: &mut [f64]);
        /// Its values at the reduction grid's wavelengths, appended to `out`.
        fn illuminant_on_grid(s: &Illuminant, out: &mut Vec<f64>);
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
    QdMediumConfig, Range, Rgb, SampledSpectrum,
};

// ---------------------------------------------------------------- shared value types

fn rgb(v: [f64; 3]) -> Rgb {
    Rgb { r: v[0], g: v[1], b: v[2] }
}

fn range_of(r: Option<(f64, f64)>) -> Range {
    r.map_or(Range { lo: 0.0, hi: 0.0 }, |(lo, hi)| Range { lo, hi })
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

// ------------------------------------------------------------ the plugins' sections

mod illuminant;
mod jung;
mod measured;
mod medium;
mod quantum_dots;
mod transport;

use illuminant::*;
use jung::*;
use measured::*;
use medium::*;
use quantum_dots::*;
use transport::*;

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
        let a = jung_rgb_albedo(&m);
        let white = spectrum_to_srgb(|_| 1.0);
        assert!((a.r - 0.5 * white[0]).abs() < 1e-12 && (a.b - 0.5 * white[2]).abs() < 1e-12);
        // the RGB parts the plugin bakes: the elastic part is r = 0.5's sRGB
        let parts = jung_rgb_parts(&m, &m);
        assert!(
            (parts.reflectance.r - 0.5 * white[0]).abs() < 1e-12
                && (parts.reflectance.b - 0.5 * white[2]).abs() < 1e-12
        );
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
        let t = qd_jit_tables(&m, 3, &[], &[400.0, 500.0, 600.0], true);
        assert_eq!((t.extra_r_spe.len(), t.extra_pass.len()), (9, 9));
        // RGB: the channels' coefficients alone, equal to those of the whole bake
        let rgb = qd_jit_tables(&m, 3, &[], &[400.0, 500.0, 600.0], false);
        assert_eq!((rgb.extra_r_spe, rgb.extra_pass), (t.extra_r_spe.clone(), t.extra_pass.clone()));
        assert!(rgb.a_tot.is_empty() && rgb.r_tot.is_empty() && rgb.lambda == t.lambda);
        assert!(t.extra_r_spe.iter().all(|r| *r >= 0.0) && t.extra_pass.iter().all(|p| *p > 0.0 && *p <= 1.0));
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
        let t = qd_jit_tables(&m, 5, &[], &[], true);
        assert!(!t.r_tot.is_empty() && t.r_tot.iter().all(|r| r.is_finite() && *r > 0.0 && *r <= 1.0));
    }
}
