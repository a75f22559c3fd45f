//! fluo_jung: Jung et al.'s dye, its colour upsampling cube and per-texel models, textured dye shapes.

use super::*;

/// Opaque `fluo_jung` material handed to C++: the dye, shared with the generic handle,
/// whose `elastic` is the base reflectance when it is given as sigmoid coefficients.
pub struct JungModel {
    pub(crate) dye: Arc<JungFluorescence>,
    pub(crate) generic: Fluorescence,
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
    pub(crate) fn reflectance(&self, lambda: f64) -> f64 {
        self.generic.elastic.as_ref().map_or(0.0, |r| r.eval(lambda))
    }
}

pub(crate) fn jung_new(config: &JungConfig) -> Result<Box<JungModel>, String> {
    guarded(|| JungModel::new(config).map(Box::new))
}

pub(crate) fn jung_default_config() -> JungConfig {
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

pub(crate) fn jung_is_fluorescent(model: &JungModel) -> bool {
    model.dye.is_fluorescent()
}

pub(crate) fn jung_to_string(model: &JungModel) -> String {
    match &model.generic.elastic {
        Some(Reflectance::Sigmoid(s)) => format!("{} with sigmoid reflectance {:?}", model.dye, s.coefficients),
        _ => model.dye.to_string(),
    }
}

pub(crate) fn jung_fluorescence(model: &JungModel) -> &Fluorescence {
    &model.generic
}

/// Opaque coefficient cube handed to C++: shared by every material that loads the same
/// file (see [`shared_cube`]).
pub struct UpsampleCube(std::sync::Arc<fluo::upsample::Cube>);

/// Cubes loaded so far, by file and its modification time and length (a rewritten file
/// is loaded again); weak, so a cube no scene uses is freed.
pub(crate) type CubeKey = (std::path::PathBuf, Option<std::time::SystemTime>, u64);
pub(crate) static CUBES: std::sync::Mutex<Vec<(CubeKey, std::sync::Weak<fluo::upsample::Cube>)>> =
    std::sync::Mutex::new(Vec::new());

/// The cube in `path`, loaded once per file and shared: a scene with many coloured
/// materials holds one copy (1.6 MB for a shipped cube) and reads it once.
pub(crate) fn shared_cube(path: &std::path::Path) -> fluo::Result<std::sync::Arc<fluo::upsample::Cube>> {
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

pub(crate) fn upsample_cube_load(space: &str, filename: &str) -> Result<Box<UpsampleCube>, String> {
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

/// The `fluo_jung` configuration of one colour's cube coefficients.
pub(crate) fn jung_config_of(c: &fluo::upsample::Coefficients) -> JungConfig {
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

pub(crate) fn upsample_lookup(
    cube: &UpsampleCube,
    rgb: &[f64],
    lookup: &str,
    fluorescence: bool,
) -> Result<JungConfig, String> {
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

pub(crate) fn jung_texture_new(
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

pub(crate) fn texel_index(tex: &JungTexture, x: i64, y: i64) -> usize {
    let (w, h) = (tex.width as i64, tex.height as i64);
    let (x, y) = (x.rem_euclid(w), y.rem_euclid(h));
    tex.texel.get((y * w + x) as usize).map_or(0, |&i| i as usize)
}

pub(crate) fn jung_texture_model(tex: &JungTexture, x: i64, y: i64) -> &JungModel {
    &tex.models[texel_index(tex, x, y).min(tex.models.len() - 1)]
}

pub(crate) fn jung_texture_rgb(tex: &JungTexture, x: i64, y: i64) -> Rgb {
    let i = texel_index(tex, x, y).min(tex.rgb.len() - 1);
    let c = &tex.rgb[i];
    Rgb { r: c.r, g: c.g, b: c.b }
}

pub(crate) fn jung_texture_representative(tex: &JungTexture) -> &JungModel {
    &tex.models[tex.representative]
}

pub(crate) fn jung_config(model: &JungModel) -> JungConfig {
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

pub(crate) fn jung_texture_is_fluorescent(tex: &JungTexture) -> bool {
    tex.models.iter().any(|m| m.dye.is_fluorescent())
}

pub(crate) fn jung_texture_distinct(tex: &JungTexture) -> usize {
    tex.models.len()
}

pub(crate) fn jung_check_values(name: &str, values: &[f32], width: usize) -> Result<(), String> {
    check_texture_values(name, values, width, fluo::models::jung::check_param_value)
}

/// Check each value of a parameter texture with `check`, naming the first failing one by
/// its texel (`width` > 0) or its position.
pub(crate) fn check_texture_values(
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

pub(crate) fn jung_rgb_parts(dye: &JungModel, base: &JungModel) -> JungRgbParts {
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
pub(crate) const MAX_JUNG_SHAPES: usize = 4096;

/// Opaque dye shapes of a `fluo_jung` with textured parameters.
pub struct JungShapes {
    models: Vec<JungModel>,
}

pub(crate) fn jung_shapes_new(peaks: &[f64], shifts: &[f64]) -> Result<Box<JungShapes>, String> {
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
        Ok(Box::new(JungShapes { models }))
    })
}

pub(crate) fn jung_shapes_len(shapes: &JungShapes) -> usize {
    shapes.models.len()
}

pub(crate) fn jung_shapes_model(shapes: &JungShapes, i: usize) -> &JungModel {
    &shapes.models[i.min(shapes.models.len() - 1)]
}

/// The texel's RGB albedo under equal-energy light: the elastic part's sRGB plus the
/// reradiation's, bounded ([`bounded_rgb_albedo`]).
pub(crate) fn jung_rgb_albedo(model: &JungModel) -> Rgb {
    let elastic = spectrum_to_srgb(|l| model.reflectance(l) * model.dye.elastic_factor(l));
    // c·Q·∫_{360}^{830} a(λ) dλ: reradiated energy per unit equal-energy irradiance.
    let p = model.dye.params();
    let w = p.concentration * p.quantum_yield * model.dye.absorption_integral_range(CIE_MIN_NM, CIE_MAX_NM);
    let reradiated = if w > 0.0 { spectrum_to_srgb(|l| w * model.dye.emission(l)) } else { [0.0; 3] };
    rgb(bounded_rgb_albedo(elastic, reradiated))
}
