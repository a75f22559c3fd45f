//! Measured reradiation (Donaldson) matrices: loaders, filtering, and the continuous
//! tabulated model behind `fluo_matrix`.
//!
//! # Data
//! A reradiation matrix D(λo, λi) gives, for monochromatic excitation of unit power at
//! λi, the fraction of it leaving in the band of width Δλo around λo (Donaldson 1954).
//! Its diagonal (λi = λo) is the ordinary reflectance ρ(λ); above it (λo > λi) is
//! fluorescent reradiation.
//!
//! Loaders ([`load_matrix`] picks one by extension):
//! * Labsphere BFC text (`.bfc`): 10 header lines (line 2 the `BFC-450 Matrix File`
//!   signature, lines 3–10 `;` comments), then `out_start out_end out_step n_in
//!   in_start in_step`, then `r:c:` and the n_in excitation wavelengths, then one row
//!   per emission wavelength (the wavelength, then n_in values), then `EOD`. Blank
//!   lines inside the data are skipped.
//! * CSV (`.csv`): a header row `lambda_o\lambda_i,λi…` (a leading `#` is allowed),
//!   then rows `λo,values…`; other `#` lines are comments.
//! * Bispectral Spectral OpenEXR (`.exr`, Fichet et al. 2021 layout): channels
//!   `T.<λ>nm` (the diagonal) and `T.<λi>nm.<λo>nm` (reradiation), wavelengths written
//!   with a `,` or no decimal separator (`T.550,000000nm`); other channels are ignored.
//!   A material is one matrix: the mean over all pixels is used.
//!
//! Every loader rejects malformed input with an error that names the file and the line
//! and column (or channel): a truncated file, a non-finite value (NaN, inf), a wrong
//! header, a wavelength off its grid. Files are read through [`crate::fileio`] (regular
//! files only, at most [`crate::fileio::MAX_MATRIX_FILE_BYTES`]); a size a header
//! claims (a BFC grid, an EXR data window) is checked against the bytes actually read
//! and a cap ([`MAX_MATRIX_ENTRIES`], [`MAX_EXR_SAMPLES`]) before anything is allocated
//! for it; entries are bounded by [`MAX_MATRIX_VALUE`] so that renders stay finite in
//! float32.
//!
//! # Filtering (Hua et al. 2022, sec. 5.1)
//! Entries below the diagonal (λo < λi, anti-Stokes) and negative entries are
//! measurement noise and are set to zero; so are negative diagonal values. Nothing else
//! is changed (no smoothing, no renormalisation; column sums slightly above 1 in a
//! measurement are kept as measured).
//!
//! # Continuous model
//! ```text
//! ρ(λ)      = piecewise-linear interpolation of the diagonal, held constant beyond its ends
//! P(λi, λo) = bilinear interpolation of D(λo_j, λi_k) / Δλo_j   for λi ≤ λo, else 0   (nm⁻¹)
//! f(λi, ωi, ωo, λo) = [ δ(λi − λo) ρ(λi) + P(λi, λo) ] / π          (diffuse)
//! ```
//! with Δλo_j the emission band width (the grid step; the mean of the neighbouring gaps
//! on an irregular grid) and P zero outside the measured rectangle. Dividing by Δλo
//! turns the band fractions into energy per nm of λo, so ∫ P(λi, λo) dλo is the
//! reradiated albedo at λi; bilinear interpolation makes P continuous in both
//! wavelengths, so the same function is evaluated, integrated and sampled.
//!
//! # Sampling (exact, tabulated)
//! For fixed λi between columns k and k+1 (weight s), P(λi, ·) = (1−s)·col_k + s·col_{k+1}
//! with col_k the piecewise-linear column: its CDF is the same mixture of the columns'
//! cumulative integrals, tabulated once per node. λo | λi is sampled by inverting that
//! CDF on [max(λi, λo_min), λo_max]: a binary search for the cell, then the exact root
//! of the quadratic inside it. λi | λo uses the rows the same way, on
//! [max(lo, λi_min), min(hi, λo, λi_max)]. No rejection, no loop beyond the search.
//!
//! # Numerical notes
//! Tables are f64; the cell quadratic is solved in the cancellation-free form
//! u = 2Δ / (f0 + √(f0² + 2mΔ)). Grids must be strictly increasing with at least
//! [`MIN_GRID_POINTS`] points and two common (diagonal) wavelengths. Uniform grids (BFC
//! files are 10 nm) are detected at load and their cells indexed directly; irregular
//! ones are bisected (the same cell either way).
//!
//! # References
//! R. Donaldson, "Spectrophotometry of fluorescent pigments", Br. J. Appl. Phys. 5, 1954.
//! Q. Hua, V. Tázlar, A. Fichet, A. Wilkie, "Efficient Storage and Importance Sampling
//! for Fluorescent Reflectance", CGF 2022. A. Fichet, R. Pacanowski, A. Wilkie, "An
//! OpenEXR Layout for Spectral Images", JCGT 10(3), 2021.

use std::fmt;
use std::path::{Path, PathBuf};

use crate::spectrum::GridIndex;
use crate::{Error, Result};

/// Fewest grid points along either wavelength axis.
pub const MIN_GRID_POINTS: usize = 2;
/// Two wavelengths closer than this are the same (diagonal matching, grid checks), nm.
pub const WAVELENGTH_TOLERANCE_NM: f64 = 1e-6;
/// Number of header lines of a Labsphere BFC file.
pub const BFC_HEADER_LINES: usize = 10;
/// Largest accepted grid (per axis): guards against absurd headers.
pub const MAX_GRID_POINTS: usize = 100_000;
/// Largest accepted matrix (λi × λo entries): 1 nm steps over 200–1200 nm on both
/// axes. A header claiming more is refused before anything is allocated for it.
pub const MAX_MATRIX_ENTRIES: usize = 1_000_000;
/// Largest accepted magnitude of a matrix entry. Measured radiance factors are O(1)
/// (a bright fluorescent white peaks near 2); an entry of 1000 already means a patch
/// returning a thousand times the light it receives. The bound keeps every product a
/// render forms with it (light × throughput × entry) finite in float32.
pub const MAX_MATRIX_VALUE: f64 = 1e3;
/// Largest accepted wavelength of a matrix grid, nm.
pub const MAX_WAVELENGTH_NM: f64 = 1e4;
/// Most samples (pixels × channels, all parts) an EXR header may claim.
pub const MAX_EXR_SAMPLES: usize = 1 << 24;
/// An EXR header may claim at most this many samples per byte of file (the best
/// lossless compression of constant data is far below it).
pub const MAX_EXR_COMPRESSION_RATIO: u128 = 1024;

/// Directory of the shared reference data: `$FLUO_SHARED_DATA`, else
/// `<repo>/../shared/data`; `None` when it does not exist.
pub fn shared_data_dir() -> Option<PathBuf> {
    let dir = match std::env::var_os("FLUO_SHARED_DATA") {
        Some(d) => PathBuf::from(d),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
    };
    dir.is_dir().then_some(dir)
}

/// The measured bispectral files in `<shared>/bispectral/` (`.bfc`, `.csv`, `.exr`), sorted.
pub fn shared_bispectral_files() -> Vec<PathBuf> {
    let Some(dir) = shared_data_dir() else { return Vec::new() };
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir.join("bispectral"))
        .map(|rd| rd.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    files.retain(|p| matches!(extension(p).as_str(), "bfc" | "csv" | "exr"));
    files.sort();
    files
}

fn extension(p: &Path) -> String {
    p.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default()
}

/// A raw reradiation matrix as read from a file.
#[derive(Debug, Clone, PartialEq)]
pub struct Donaldson {
    /// Where it came from (file name), for messages.
    pub source: String,
    /// Excitation wavelengths λi (columns), nm, strictly increasing.
    pub lambda_i: Vec<f64>,
    /// Emission wavelengths λo (rows), nm, strictly increasing.
    pub lambda_o: Vec<f64>,
    /// `values[j * lambda_i.len() + k]` = D(λo_j, λi_k), as measured.
    pub values: Vec<f64>,
}

impl Donaldson {
    /// Check the grids and values (finite, strictly increasing, sizes match).
    pub fn new(source: &str, lambda_i: Vec<f64>, lambda_o: Vec<f64>, values: Vec<f64>) -> Result<Self> {
        for (name, g) in [("lambda_i", &lambda_i), ("lambda_o", &lambda_o)] {
            if g.len() < MIN_GRID_POINTS || g.len() > MAX_GRID_POINTS {
                return Err(Error::data(format!(
                    "{source}: {name} grid has {} wavelengths, valid is [{MIN_GRID_POINTS}, {MAX_GRID_POINTS}]",
                    g.len()
                )));
            }
            if let Some(w) = g.windows(2).find(|w| !(w[1] > w[0] + WAVELENGTH_TOLERANCE_NM)) {
                return Err(Error::data(format!(
                    "{source}: {name} grid is not strictly increasing ({} then {})",
                    w[0], w[1]
                )));
            }
            if let Some(x) = g.iter().find(|x| !(x.is_finite() && **x > 0.0 && **x <= MAX_WAVELENGTH_NM)) {
                return Err(Error::data(format!(
                    "{source}: {name} wavelength {} nm: valid range is (0, {MAX_WAVELENGTH_NM}] nm",
                    crate::num(*x)
                )));
            }
        }
        if values.len() != lambda_i.len() * lambda_o.len() {
            return Err(Error::data(format!(
                "{source}: {} values for a {} x {} grid",
                values.len(),
                lambda_o.len(),
                lambda_i.len()
            )));
        }
        if let Some(i) = values.iter().position(|v| !(v.abs() <= MAX_MATRIX_VALUE)) {
            let n = lambda_i.len();
            return Err(Error::data(format!(
                "{source}: value {} at lambda_o = {} nm, lambda_i = {} nm: valid range is [-{MAX_MATRIX_VALUE}, {MAX_MATRIX_VALUE}] (finite)",
                crate::num(values[i]),
                lambda_o[i / n],
                lambda_i[i % n],
            )));
        }
        Ok(Self { source: source.to_string(), lambda_i, lambda_o, values })
    }

    /// D(λo_j, λi_k).
    pub fn at(&self, j: usize, k: usize) -> f64 {
        self.values[j * self.lambda_i.len() + k]
    }

    /// The diagonal: (λ, D(λ, λ)) for every wavelength on both grids.
    pub fn diagonal(&self) -> Vec<(f64, f64)> {
        let mut out = Vec::new();
        for (j, &lo) in self.lambda_o.iter().enumerate() {
            if let Some(k) = self.lambda_i.iter().position(|&li| (li - lo).abs() <= WAVELENGTH_TOLERANCE_NM) {
                out.push((lo, self.at(j, k)));
            }
        }
        out
    }
}

/// A matrix after the paper's filtering (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Filtered {
    /// Source label.
    pub source: String,
    /// λi grid, nm.
    pub lambda_i: Vec<f64>,
    /// λo grid, nm.
    pub lambda_o: Vec<f64>,
    /// Diagonal wavelengths, nm.
    pub diagonal_nm: Vec<f64>,
    /// Diagonal reflectance ρ, clamped to ≥ 0.
    pub diagonal: Vec<f64>,
    /// Off-diagonal D (row-major like [`Donaldson::values`]): zero on and below the
    /// diagonal and where negative.
    pub off: Vec<f64>,
    /// Emission band widths Δλo_j, nm.
    pub band_nm: Vec<f64>,
}

/// Band widths of a grid: the step on a regular grid, the mean neighbouring gap otherwise.
fn band_widths(g: &[f64]) -> Vec<f64> {
    let n = g.len();
    (0..n)
        .map(|j| match j {
            0 => g[1] - g[0],
            _ if j == n - 1 => g[n - 1] - g[n - 2],
            _ => 0.5 * (g[j + 1] - g[j - 1]),
        })
        .collect()
}

impl Filtered {
    /// Apply the filtering of Hua et al. sec. 5.1.
    pub fn new(d: &Donaldson) -> Result<Self> {
        let diag = d.diagonal();
        if diag.len() < MIN_GRID_POINTS {
            return Err(Error::data(format!(
                "{}: only {} wavelengths are on both grids; the diagonal (reflectance) needs at least {MIN_GRID_POINTS}",
                d.source,
                diag.len()
            )));
        }
        let n = d.lambda_i.len();
        let mut off = vec![0.0; d.values.len()];
        for (j, &lo) in d.lambda_o.iter().enumerate() {
            for (k, &li) in d.lambda_i.iter().enumerate() {
                let v = d.at(j, k);
                if lo > li + WAVELENGTH_TOLERANCE_NM && v > 0.0 {
                    off[j * n + k] = v;
                }
            }
        }
        Ok(Self {
            source: d.source.clone(),
            lambda_i: d.lambda_i.clone(),
            lambda_o: d.lambda_o.clone(),
            diagonal_nm: diag.iter().map(|p| p.0).collect(),
            diagonal: diag.iter().map(|p| p.1.max(0.0)).collect(),
            off,
            band_nm: band_widths(&d.lambda_o),
        })
    }
}

/// Read a matrix file, choosing the loader by extension (`.bfc`, `.csv`, `.exr`).
pub fn load_matrix(path: impl AsRef<Path>) -> Result<Donaldson> {
    let path = path.as_ref();
    let label = path.display().to_string();
    match extension(path).as_str() {
        "exr" => read_exr(path),
        ext @ ("bfc" | "csv") => {
            let text = crate::fileio::read_text(path, crate::fileio::MAX_MATRIX_FILE_BYTES, "reradiation matrix")?;
            if ext == "bfc" {
                parse_bfc(&text, &label)
            } else {
                parse_csv(&text, &label)
            }
        }
        other => Err(Error::param(
            "filename",
            format!("\"{label}\" (extension \"{other}\")"),
            "a reradiation matrix file: .bfc (Labsphere), .csv or .exr (bispectral Spectral OpenEXR)",
        )),
    }
}

fn parse_number(field: &str, source: &str, line: usize, column: usize) -> Result<f64> {
    let v: f64 = field
        .trim()
        .parse()
        .map_err(|_| Error::data(format!("{source}: line {line}, column {column}: \"{field}\" is not a number")))?;
    if !v.is_finite() {
        return Err(Error::data(format!("{source}: line {line}, column {column}: \"{field}\" is not a finite number")));
    }
    Ok(v)
}

/// `start + i·step` for i < n, checked against `given` (a header's wavelength list).
fn check_grid(given: &[f64], start: f64, step: f64, what: &str, source: &str, line: usize) -> Result<()> {
    for (i, &g) in given.iter().enumerate() {
        let want = start + step * i as f64;
        if (g - want).abs() > 1e-6 * step.abs().max(1.0) {
            return Err(Error::data(format!(
                "{source}: line {line}, column {}: {what} wavelength {g} nm, expected {want} nm from the header",
                i + 2
            )));
        }
    }
    Ok(())
}

/// Parse a Labsphere BFC matrix (format in the module docs). `source` labels errors.
pub fn parse_bfc(text: &str, source: &str) -> Result<Donaldson> {
    let lines: Vec<&str> = text.lines().map(|l| l.trim_end_matches('\r')).collect();
    let truncated = |what: &str| Error::data(format!("{source}: truncated file: {what}"));
    if let Some(sig) = lines.get(1).filter(|l| !l.trim().starts_with("BFC")) {
        return Err(Error::data(format!(
            "{source}: line 2: wrong header \"{}\", expected the Labsphere signature \"BFC-450 Matrix File\"",
            sig.trim()
        )));
    }
    if lines.len() < BFC_HEADER_LINES {
        return Err(truncated(&format!("{} lines, the BFC header alone has {BFC_HEADER_LINES}", lines.len())));
    }
    for (i, l) in lines.iter().enumerate().take(BFC_HEADER_LINES).skip(2) {
        if !l.trim_start().starts_with(';') {
            return Err(Error::data(format!(
                "{source}: line {}: wrong header \"{}\", expected a \";\" comment (header lines 3-{BFC_HEADER_LINES})",
                i + 1,
                l.trim()
            )));
        }
    }
    // Line 11: out_start out_end out_step n_in in_start in_step.
    let spec_line = BFC_HEADER_LINES + 1;
    let spec = lines.get(BFC_HEADER_LINES).ok_or_else(|| truncated("no grid line (line 11)"))?;
    let f: Vec<&str> = spec.split_whitespace().collect();
    if f.len() != 6 {
        return Err(Error::data(format!(
            "{source}: line {spec_line}: wrong header \"{}\", expected 6 numbers: out_start out_end out_step n_in in_start in_step",
            spec.trim()
        )));
    }
    let nums: Vec<f64> =
        f.iter().enumerate().map(|(c, x)| parse_number(x, source, spec_line, c + 1)).collect::<Result<_>>()?;
    let [out_start, out_end, out_step, n_in, in_start, in_step] =
        [nums[0], nums[1], nums[2], nums[3], nums[4], nums[5]];
    let grid_err = |m: String| Error::data(format!("{source}: line {spec_line}: {m}"));
    if !(out_step > 0.0 && in_step > 0.0) {
        return Err(grid_err(format!("steps must be positive (out_step = {out_step}, in_step = {in_step})")));
    }
    let n_out_f = (out_end - out_start) / out_step + 1.0;
    if !(n_out_f >= MIN_GRID_POINTS as f64
        && n_out_f <= MAX_GRID_POINTS as f64
        && (n_out_f - n_out_f.round()).abs() < 1e-6)
    {
        return Err(grid_err(format!(
            "({out_start}..{out_end} step {out_step}) is not a whole number of emission steps"
        )));
    }
    if !(n_in >= MIN_GRID_POINTS as f64 && n_in <= MAX_GRID_POINTS as f64 && n_in.fract() == 0.0) {
        return Err(grid_err(format!(
            "n_in = {n_in}: valid range is whole numbers in [{MIN_GRID_POINTS}, {MAX_GRID_POINTS}]"
        )));
    }
    let (n_out, n_in) = (n_out_f.round() as usize, n_in as usize);
    // Each entry takes at least two bytes (a digit and a separator): a header claiming
    // more than the text can hold is refused before allocating for it.
    if n_out * n_in > MAX_MATRIX_ENTRIES || n_out * n_in > text.len() / 2 {
        return Err(grid_err(format!(
            "the header claims a {n_out} × {n_in} matrix, which a file of {} bytes cannot hold (at most {MAX_MATRIX_ENTRIES} entries)",
            text.len()
        )));
    }

    // Line 12: r:c: followed by the excitation wavelengths.
    let head_line = spec_line + 1;
    let head = lines.get(head_line - 1).ok_or_else(|| truncated("no \"r:c:\" line (line 12)"))?;
    let h: Vec<&str> = head.split_whitespace().collect();
    if h.first() != Some(&"r:c:") {
        return Err(Error::data(format!(
            "{source}: line {head_line}: wrong header, expected \"r:c:\" and {n_in} wavelengths"
        )));
    }
    if h.len() != n_in + 1 {
        return Err(Error::data(format!(
            "{source}: line {head_line}: {} excitation wavelengths, the header (line {spec_line}) says {n_in}",
            h.len() - 1
        )));
    }
    let lambda_i: Vec<f64> =
        h[1..].iter().enumerate().map(|(c, x)| parse_number(x, source, head_line, c + 2)).collect::<Result<_>>()?;
    check_grid(&lambda_i, in_start, in_step, "excitation", source, head_line)?;

    let mut lambda_o = Vec::with_capacity(n_out);
    let mut values = Vec::with_capacity(n_out * n_in);
    let mut idx = head_line; // 0-based index of the next line
    while lambda_o.len() < n_out {
        let Some(l) = lines.get(idx) else {
            return Err(truncated(&format!("{} of {n_out} emission rows before the end of the file", lambda_o.len())));
        };
        let line_no = idx + 1;
        idx += 1;
        if l.trim().is_empty() {
            continue;
        }
        if l.trim() == "EOD" {
            return Err(truncated(&format!("line {line_no}: EOD after {} of {n_out} emission rows", lambda_o.len())));
        }
        let cols: Vec<&str> = l.split_whitespace().collect();
        if cols.len() != n_in + 1 {
            return Err(Error::data(format!(
                "{source}: line {line_no}: {} values, expected the emission wavelength and {n_in} values",
                cols.len()
            )));
        }
        let lo = parse_number(cols[0], source, line_no, 1)?;
        let want = out_start + out_step * lambda_o.len() as f64;
        if (lo - want).abs() > 1e-6 * out_step.max(1.0) {
            return Err(Error::data(format!(
                "{source}: line {line_no}, column 1: emission wavelength {lo} nm, expected {want} nm"
            )));
        }
        lambda_o.push(lo);
        for (c, x) in cols[1..].iter().enumerate() {
            values.push(parse_number(x, source, line_no, c + 2)?);
        }
    }
    // The data must end with EOD (blank lines allowed before it).
    loop {
        match lines.get(idx) {
            None => return Err(truncated(&format!("no \"EOD\" after the {n_out} emission rows"))),
            Some(l) if l.trim().is_empty() => idx += 1,
            Some(l) if l.trim() == "EOD" => break,
            Some(l) => {
                return Err(Error::data(format!(
                    "{source}: line {}: \"{}\" after the {n_out} emission rows, expected \"EOD\"",
                    idx + 1,
                    l.chars().take(40).collect::<String>()
                )))
            }
        }
    }
    Donaldson::new(source, lambda_i, lambda_o, values)
}

/// Parse a CSV matrix (format in the module docs). `source` labels errors.
pub fn parse_csv(text: &str, source: &str) -> Result<Donaldson> {
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim_end_matches('\r')));
    // The header is the first line naming the axes; `#` comment lines may precede it.
    let is_header = |l: &str| l.trim().trim_start_matches('#').trim().to_ascii_lowercase().starts_with("lambda");
    let (head_no, head) = lines
        .by_ref()
        .find(|(_, l)| !l.trim().is_empty() && (is_header(l) || !l.trim().starts_with('#')))
        .ok_or_else(|| Error::data(format!("{source}: empty file (no header line)")))?;
    let head = head.trim().trim_start_matches('#').trim();
    let fields: Vec<&str> = head.split(',').collect();
    if !fields[0].to_ascii_lowercase().contains("lambda") || fields.len() < MIN_GRID_POINTS + 1 {
        return Err(Error::data(format!(
            "{source}: line {head_no}: wrong header \"{}\", expected \"lambda_o\\lambda_i,<excitation wavelengths>\"",
            head.chars().take(40).collect::<String>()
        )));
    }
    let lambda_i: Vec<f64> =
        fields[1..].iter().enumerate().map(|(c, x)| parse_number(x, source, head_no, c + 2)).collect::<Result<_>>()?;
    let (mut lambda_o, mut values) = (Vec::new(), Vec::new());
    for (no, l) in lines {
        let t = l.trim();
        if t.is_empty() || t.starts_with('#') {
            continue;
        }
        let cols: Vec<&str> = t.split(',').collect();
        if cols.len() != lambda_i.len() + 1 {
            return Err(Error::data(format!(
                "{source}: line {no}: {} fields, expected the emission wavelength and {} values (truncated?)",
                cols.len(),
                lambda_i.len()
            )));
        }
        lambda_o.push(parse_number(cols[0], source, no, 1)?);
        for (c, x) in cols[1..].iter().enumerate() {
            values.push(parse_number(x, source, no, c + 2)?);
        }
    }
    Donaldson::new(source, lambda_i, lambda_o, values)
}

/// Parse a wavelength token of a spectral EXR channel name: `550nm`, `550,5nm`.
fn exr_wavelength(token: &str) -> Option<f64> {
    let v: f64 = token.strip_suffix("nm")?.replace(',', ".").parse().ok()?;
    (v.is_finite() && v > 0.0).then_some(v)
}

/// Classify an EXR channel name: `Some((λi, Some(λo)))` for reradiation,
/// `Some((λ, None))` for the diagonal, `None` for other channels.
fn exr_channel(name: &str) -> Option<(f64, Option<f64>)> {
    let parts: Vec<&str> = name.split('.').collect();
    let t = parts.iter().rposition(|p| *p == "T")?;
    match &parts[t + 1..] {
        [a] => Some((exr_wavelength(a)?, None)),
        [a, b] => Some((exr_wavelength(a)?, Some(exr_wavelength(b)?))),
        _ => None,
    }
}

/// Read a bispectral Spectral OpenEXR file (layout in the module docs).
pub fn read_exr(path: &Path) -> Result<Donaldson> {
    let source = path.display().to_string();
    let bytes = crate::fileio::read_bytes(path, crate::fileio::MAX_MATRIX_FILE_BYTES, "reradiation matrix")?;
    // The headers first: `exr` allocates what a header's data window claims, so the
    // claim is checked against a cap and against what the bytes can hold.
    let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(&bytes), false)
        .map_err(|e| Error::data(format!("{source}: not a readable OpenEXR file: {e}")))?;
    let mut samples: u128 = 0;
    for header in meta.headers.iter() {
        let (w, h) = (header.layer_size.width() as u128, header.layer_size.height() as u128);
        samples += w * h * header.channels.list.len() as u128;
    }
    let plausible = (bytes.len() as u128).saturating_mul(MAX_EXR_COMPRESSION_RATIO);
    if samples > MAX_EXR_SAMPLES as u128 || samples > plausible {
        return Err(Error::data(format!(
            "{source}: the header claims {samples} samples (data window × channels) in a file of {} bytes; at most {} are read",
            bytes.len(),
            MAX_EXR_SAMPLES.min(plausible.min(usize::MAX as u128) as usize)
        )));
    }
    use exr::prelude::{ReadChannels, ReadLayers};
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(&bytes))
        .map_err(|e| Error::data(format!("{source}: not a readable OpenEXR file: {e}")))?;
    // (λi, λo, value) triplets; the diagonal has λi = λo.
    let mut entries: Vec<(f64, f64, f64)> = Vec::new();
    let mut malformed = Vec::new();
    for layer in &image.layer_data {
        for ch in &layer.channel_data.list {
            let name = ch.name.to_string();
            let looks_spectral = name.split('.').any(|p| p == "T");
            let Some((a, b)) = exr_channel(&name) else {
                if looks_spectral {
                    malformed.push(name);
                }
                continue;
            };
            let n = ch.sample_data.len();
            let mut sum = 0.0;
            for v in ch.sample_data.values_as_f32() {
                if !v.is_finite() {
                    return Err(Error::data(format!("{source}: channel \"{name}\": value {v} is not finite")));
                }
                sum += f64::from(v);
            }
            let mean = if n > 0 { sum / n as f64 } else { 0.0 };
            entries.push((a, b.unwrap_or(a), mean));
        }
    }
    if let Some(name) = malformed.first() {
        return Err(Error::data(format!(
            "{source}: channel \"{name}\": expected T.<lambda>nm or T.<lambda_i>nm.<lambda_o>nm"
        )));
    }
    if entries.is_empty() {
        return Err(Error::data(format!(
            "{source}: no bispectral channels (T.<lambda>nm, T.<lambda_i>nm.<lambda_o>nm)"
        )));
    }
    let uniq = |mut v: Vec<f64>| {
        v.sort_by(|a, b| a.total_cmp(b));
        v.dedup_by(|a, b| (*a - *b).abs() <= WAVELENGTH_TOLERANCE_NM);
        v
    };
    let lambda_i = uniq(entries.iter().map(|e| e.0).collect());
    let lambda_o = uniq(entries.iter().map(|e| e.1).collect());
    let find = |g: &[f64], x: f64| g.iter().position(|&y| (y - x).abs() <= WAVELENGTH_TOLERANCE_NM).unwrap_or(0);
    let mut values = vec![0.0; lambda_i.len() * lambda_o.len()];
    for (a, b, v) in entries {
        values[find(&lambda_o, b) * lambda_i.len() + find(&lambda_i, a)] = v;
    }
    Donaldson::new(&source, lambda_i, lambda_o, values)
}

/// Write a matrix as a bispectral Spectral OpenEXR file (1×1 pixel; the diagonal as
/// `T.<λ>nm`, reradiation above it as `T.<λi>nm.<λo>nm`, wavelengths with a `,`).
pub fn write_exr(d: &Donaldson, path: &Path) -> Result<()> {
    use exr::prelude::{
        AnyChannel, AnyChannels, Encoding, FlatSamples, Image, Layer, LayerAttributes, SmallVec, WritableImage,
    };
    let fmt_nm = |x: f64| format!("{x:.6}nm").replace('.', ",");
    let mut list: SmallVec<[AnyChannel<FlatSamples>; 4]> = SmallVec::new();
    for (j, &lo) in d.lambda_o.iter().enumerate() {
        for (k, &li) in d.lambda_i.iter().enumerate() {
            let v = d.at(j, k) as f32;
            let name = if (li - lo).abs() <= WAVELENGTH_TOLERANCE_NM {
                format!("T.{}", fmt_nm(li))
            } else if lo > li && v != 0.0 {
                format!("T.{}.{}", fmt_nm(li), fmt_nm(lo))
            } else {
                continue;
            };
            list.push(AnyChannel::new(name.as_str(), FlatSamples::F32(vec![v])));
        }
    }
    let layer = Layer::new((1, 1), LayerAttributes::named(""), Encoding::UNCOMPRESSED, AnyChannels::sort(list));
    Image::from_layer(layer).write().to_file(path).map_err(|e| Error::Io(format!("{}: {e}", path.display())))
}

/// Locate `x` on a strictly increasing grid with its [`GridIndex`]: (cell index,
/// fraction in [0, 1]); `None` outside `[g_0, g_last]`.
#[inline]
fn locate(g: &[f64], index: GridIndex, x: f64) -> Option<(usize, f64)> {
    let n = g.len();
    if !(x >= g[0] && x <= g[n - 1]) {
        return None;
    }
    let j = index.cell(g, x);
    Some((j, ((x - g[j]) / (g[j + 1] - g[j])).clamp(0.0, 1.0)))
}

/// A tabulated piecewise-linear function: values and cumulative integrals at the grid
/// nodes, read with a stride from a shared table.
#[derive(Clone, Copy)]
struct Tab<'a> {
    values: &'a [f64],
    cumul: &'a [f64],
    offset: usize,
    stride: usize,
}

impl Tab<'_> {
    fn v(&self, j: usize) -> f64 {
        self.values[self.offset + j * self.stride]
    }
    fn c(&self, j: usize) -> f64 {
        self.cumul[self.offset + j * self.stride]
    }
}

/// (1 − s)·A + s·B on grid `x`: the slice of the bilinear interpolant, with its exact CDF.
struct Slice<'a> {
    x: &'a [f64],
    index: GridIndex,
    a: Tab<'a>,
    b: Tab<'a>,
    s: f64,
}

impl Slice<'_> {
    fn v(&self, j: usize) -> f64 {
        (1.0 - self.s) * self.a.v(j) + self.s * self.b.v(j)
    }
    fn c(&self, j: usize) -> f64 {
        (1.0 - self.s) * self.a.c(j) + self.s * self.b.c(j)
    }
    /// ∫_{x_0}^{x} of the slice (x clamped to the grid).
    fn cdf(&self, x: f64) -> f64 {
        self.cdf_cell(x).0
    }
    /// [`Self::cdf`] and the cell of x (clamped to the grid), from one lookup.
    fn cdf_cell(&self, x: f64) -> (f64, usize) {
        let n = self.x.len();
        if !(x > self.x[0]) {
            return (0.0, 0);
        }
        if x >= self.x[n - 1] {
            return (self.c(n - 1), n - 2);
        }
        let (j, t) = locate(self.x, self.index, x).unwrap_or((0, 0.0));
        let f0 = self.v(j);
        let fx = (1.0 - t) * f0 + t * self.v(j + 1);
        (self.c(j) + 0.5 * (x - self.x[j]) * (f0 + fx), j)
    }
    /// ∫_{lo}^{hi} of the slice.
    fn mass(&self, lo: f64, hi: f64) -> f64 {
        if !(hi > lo) {
            return 0.0;
        }
        (self.cdf(hi) - self.cdf(lo)).max(0.0)
    }
    /// Sample x ∝ slice on [lo, hi] by exact inversion: (x, pdf).
    fn sample(&self, lo: f64, hi: f64, xi: f64) -> Option<(f64, f64)> {
        let n = self.x.len();
        let (lo, hi) = (lo.max(self.x[0]), hi.min(self.x[n - 1]));
        if !(hi > lo) {
            return None;
        }
        let ((c_lo, j_lo), (c_hi, j_hi)) = (self.cdf_cell(lo), self.cdf_cell(hi));
        let mass = c_hi - c_lo;
        if !(mass > 0.0) {
            return None;
        }
        let target = c_lo + xi.clamp(0.0, 1.0) * mass;
        // Cell: the last node at or below `target` among those spanning [lo, hi].
        let (mut a, mut b) = (j_lo, j_hi); // invariant: answer in [a, b]
        while a < b {
            let m = (a + b).div_ceil(2);
            if self.c(m) <= target {
                a = m;
            } else {
                b = m - 1;
            }
        }
        let j = a;
        let h = self.x[j + 1] - self.x[j];
        let (f0, f1) = (self.v(j), self.v(j + 1));
        let delta = (target - self.c(j)).clamp(0.0, 0.5 * h * (f0 + f1));
        let m = (f1 - f0) / h;
        let disc = (f0 * f0 + 2.0 * m * delta).max(0.0);
        let denom = f0 + disc.sqrt();
        let u = if denom > 0.0 { 2.0 * delta / denom } else { 0.0 };
        let x = (self.x[j] + u).clamp(lo.max(self.x[j]), hi.min(self.x[j + 1]));
        // The slice at x, in its cell j (continuous at the nodes: no second lookup).
        let t = ((x - self.x[j]) / h).clamp(0.0, 1.0);
        let pdf = ((1.0 - t) * f0 + t * f1) / mass;
        (pdf > 0.0 && pdf.is_finite()).then_some((x, pdf))
    }
}

/// Cumulative trapezoid integrals of piecewise-linear data along one axis.
fn cumulative(x: &[f64], v: impl Fn(usize) -> f64) -> Vec<f64> {
    let mut out = Vec::with_capacity(x.len());
    let mut acc = 0.0;
    out.push(0.0);
    for j in 1..x.len() {
        acc += 0.5 * (x[j] - x[j - 1]) * (v(j - 1) + v(j));
        out.push(acc);
    }
    out
}

/// The continuous tabulated model of a filtered matrix (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct MatrixModel {
    source: String,
    lambda_i: Vec<f64>,
    lambda_o: Vec<f64>,
    diagonal_nm: Vec<f64>,
    diagonal: Vec<f64>,
    /// Cell lookup on `lambda_i`, `lambda_o` and `diagonal_nm` (direct on uniform grids).
    index_i: GridIndex,
    index_o: GridIndex,
    index_diagonal: GridIndex,
    /// P at the nodes, nm⁻¹: `p[j * n_i + k]` = D_off(λo_j, λi_k) / Δλo_j.
    p: Vec<f64>,
    /// Column cumulative integrals over λo, same layout as `p` (stride n_i down a column).
    col_cdf: Vec<f64>,
    /// Row cumulative integrals over λi, same layout as `p`.
    row_cdf: Vec<f64>,
    excitation_range: Option<(f64, f64)>,
    emission_range: Option<(f64, f64)>,
}

impl MatrixModel {
    /// Load, filter and bake a matrix file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self> {
        Self::new(&Filtered::new(&load_matrix(path)?)?)
    }

    /// Bake the tables of a filtered matrix.
    pub fn new(f: &Filtered) -> Result<Self> {
        let (ni, no) = (f.lambda_i.len(), f.lambda_o.len());
        let mut p = vec![0.0; ni * no];
        for j in 0..no {
            for k in 0..ni {
                p[j * ni + k] = f.off[j * ni + k] / f.band_nm[j];
            }
        }
        Ok(Self::baked(
            f.source.clone(),
            f.lambda_i.clone(),
            f.lambda_o.clone(),
            f.diagonal_nm.clone(),
            f.diagonal.clone(),
            p,
        ))
    }

    /// The same material with the reradiation P at the nodes replaced by `p` (nm⁻¹, the
    /// layout of [`MatrixModel::row_tables`]): every entry finite and ≥ 0, one per node.
    pub fn with_reradiation(&self, p: &[f64]) -> Result<Self> {
        let n = self.lambda_i.len() * self.lambda_o.len();
        if p.len() != n {
            return Err(Error::param("reradiation", format!("{} entries", p.len()), format!("{n} (λo × λi nodes)")));
        }
        // as a file's entries: D = P·Δλo_j within MAX_MATRIX_VALUE (renders stay finite in f32)
        let bands = band_widths(&self.lambda_o);
        let ni = self.lambda_i.len();
        for (i, v) in p.iter().enumerate() {
            let max = MAX_MATRIX_VALUE / bands[i / ni];
            if !(v.is_finite() && *v >= 0.0 && *v <= max) {
                return Err(Error::param("reradiation", format!("{v} at entry {i}"), format!("[0, {max}] (nm⁻¹)")));
            }
        }
        Ok(Self::baked(
            self.source.clone(),
            self.lambda_i.clone(),
            self.lambda_o.clone(),
            self.diagonal_nm.clone(),
            self.diagonal.clone(),
            p.to_vec(),
        ))
    }

    /// The model of reradiation `p` at the nodes of the grids: its running integrals and
    /// supports.
    fn baked(
        source: String,
        lambda_i: Vec<f64>,
        lambda_o: Vec<f64>,
        diagonal_nm: Vec<f64>,
        diagonal: Vec<f64>,
        p: Vec<f64>,
    ) -> Self {
        let (ni, no) = (lambda_i.len(), lambda_o.len());
        let mut col_cdf = vec![0.0; ni * no];
        for k in 0..ni {
            let c = cumulative(&lambda_o, |j| p[j * ni + k]);
            for j in 0..no {
                col_cdf[j * ni + k] = c[j];
            }
        }
        let mut row_cdf = vec![0.0; ni * no];
        for j in 0..no {
            let c = cumulative(&lambda_i, |k| p[j * ni + k]);
            row_cdf[j * ni..(j + 1) * ni].copy_from_slice(&c);
        }
        // Support: the nodes with mass, widened by one cell (the interpolant's reach).
        let support = |g: &[f64], has: &dyn Fn(usize) -> bool| {
            let idx: Vec<usize> = (0..g.len()).filter(|&i| has(i)).collect();
            match (idx.first(), idx.last()) {
                (Some(&a), Some(&b)) => Some((g[a.saturating_sub(1)], g[(b + 1).min(g.len() - 1)])),
                _ => None,
            }
        };
        let excitation_range = support(&lambda_i, &|k| (0..no).any(|j| p[j * ni + k] > 0.0));
        let emission_range = support(&lambda_o, &|j| (0..ni).any(|k| p[j * ni + k] > 0.0));
        Self {
            source,
            index_i: GridIndex::new(&lambda_i),
            index_o: GridIndex::new(&lambda_o),
            index_diagonal: GridIndex::new(&diagonal_nm),
            lambda_i,
            lambda_o,
            diagonal_nm,
            diagonal,
            p,
            col_cdf,
            row_cdf,
            excitation_range,
            emission_range,
        }
    }

    /// Source file.
    pub fn source(&self) -> &str {
        &self.source
    }
    /// λi grid, nm.
    pub fn lambda_i(&self) -> &[f64] {
        &self.lambda_i
    }
    /// λo grid, nm.
    pub fn lambda_o(&self) -> &[f64] {
        &self.lambda_o
    }
    /// Diagonal wavelengths and reflectance values.
    pub fn diagonal(&self) -> (&[f64], &[f64]) {
        (&self.diagonal_nm, &self.diagonal)
    }
    /// P at the nodes (nm⁻¹, `p[j·n_i + k]` = P(λi_k, λo_j)) and the running integrals of
    /// its rows over λi (same layout): what the vectorised variants sample λi | λo from.
    pub fn row_tables(&self) -> (&[f64], &[f64]) {
        (&self.p, &self.row_cdf)
    }
    /// Whether any light is reradiated.
    pub fn is_fluorescent(&self) -> bool {
        self.excitation_range.is_some()
    }
    /// Excitation wavelengths that re-emit, nm.
    pub fn excitation_support(&self) -> Option<(f64, f64)> {
        self.excitation_range
    }
    /// Wavelengths re-emitted, nm.
    pub fn emission_support(&self) -> Option<(f64, f64)> {
        self.emission_range
    }

    /// Elastic albedo ρ(λ): the interpolated diagonal, constant beyond its ends.
    pub fn reflectance(&self, lambda: f64) -> f64 {
        interp_indexed(&self.diagonal_nm, self.index_diagonal, &self.diagonal, lambda)
    }

    fn locate_i(&self, lambda_i: f64) -> Option<(usize, f64)> {
        locate(&self.lambda_i, self.index_i, lambda_i)
    }

    fn locate_o(&self, lambda_o: f64) -> Option<(usize, f64)> {
        locate(&self.lambda_o, self.index_o, lambda_o)
    }

    /// P(λi, λo), nm⁻¹ (zero for λi > λo and outside the grids).
    pub fn reradiation(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        if lambda_i > lambda_o {
            return 0.0;
        }
        let (Some((k, s)), Some((j, t))) = (self.locate_i(lambda_i), self.locate_o(lambda_o)) else {
            return 0.0;
        };
        let ni = self.lambda_i.len();
        let at = |j: usize, k: usize| self.p[j * ni + k];
        (1.0 - t) * ((1.0 - s) * at(j, k) + s * at(j, k + 1)) + t * ((1.0 - s) * at(j + 1, k) + s * at(j + 1, k + 1))
    }

    /// The slice P(λi, ·) over λo (unmasked; callers bound it below by λi).
    fn column_slice(&self, lambda_i: f64) -> Option<Slice<'_>> {
        let (k, s) = self.locate_i(lambda_i)?;
        let ni = self.lambda_i.len();
        let tab = |k| Tab { values: &self.p, cumul: &self.col_cdf, offset: k, stride: ni };
        Some(Slice { x: &self.lambda_o, index: self.index_o, a: tab(k), b: tab(k + 1), s })
    }

    /// The slice P(·, λo) over λi (unmasked; callers bound it above by λo).
    fn row_slice(&self, lambda_o: f64) -> Option<Slice<'_>> {
        let (j, t) = self.locate_o(lambda_o)?;
        let ni = self.lambda_i.len();
        let tab = |j: usize| Tab { values: &self.p, cumul: &self.row_cdf, offset: j * ni, stride: 1 };
        Some(Slice { x: &self.lambda_i, index: self.index_i, a: tab(j), b: tab(j + 1), s: t })
    }

    /// ∫_{lo}^{min(hi, λo)} P(λi, λo) dλi: reradiated albedo at λo from unit excitation over [lo, hi].
    pub fn absorbed_into(&self, lambda_o: f64, lo: f64, hi: f64) -> f64 {
        self.row_slice(lambda_o).map_or(0.0, |s| s.mass(lo, hi.min(lambda_o)))
    }

    /// ∫ P(λi, λo) dλo over λo ≥ λi: reradiated albedo at λi.
    pub fn reradiated_albedo(&self, lambda_i: f64) -> f64 {
        let top = self.lambda_o[self.lambda_o.len() - 1];
        self.column_slice(lambda_i).map_or(0.0, |s| s.mass(lambda_i, top))
    }

    /// Sample λo ∝ P(λi, ·): (λo, pdf per nm), or `None` if nothing is re-emitted.
    pub fn sample_emission(&self, lambda_i: f64, xi: f64) -> Option<(f64, f64)> {
        let top = self.lambda_o[self.lambda_o.len() - 1];
        self.column_slice(lambda_i)?.sample(lambda_i, top, xi)
    }

    /// pdf of [`Self::sample_emission`].
    pub fn emission_pdf(&self, lambda_i: f64, lambda_o: f64) -> f64 {
        let m = self.reradiated_albedo(lambda_i);
        if m > 0.0 {
            self.reradiation(lambda_i, lambda_o) / m
        } else {
            0.0
        }
    }

    /// Sample λi ∝ P(·, λo) on [lo, min(hi, λo)]: (λi, pdf per nm), or `None`.
    pub fn sample_excitation(&self, lambda_o: f64, xi: f64, lo: f64, hi: f64) -> Option<(f64, f64)> {
        self.row_slice(lambda_o)?.sample(lo, hi.min(lambda_o), xi)
    }

    /// pdf of [`Self::sample_excitation`].
    pub fn excitation_pdf(&self, lambda_o: f64, lambda_i: f64, lo: f64, hi: f64) -> f64 {
        if !(lambda_i >= lo && lambda_i <= hi.min(lambda_o)) {
            return 0.0;
        }
        let m = self.absorbed_into(lambda_o, lo, hi);
        if m > 0.0 {
            self.reradiation(lambda_i, lambda_o) / m
        } else {
            0.0
        }
    }

    /// ∬ P dλi dλo over the whole domain (exact for the interpolant up to the 0.25 nm
    /// trapezoid in λo across the diagonal cells), nm.
    pub fn total_reradiation(&self) -> f64 {
        let (lo, hi) = (self.lambda_o[0], self.lambda_o[self.lambda_o.len() - 1]);
        let n = (((hi - lo) / TOTAL_STEP_NM).ceil() as usize).max(1);
        let h = (hi - lo) / n as f64;
        (0..=n)
            .map(|i| {
                let w = if i == 0 || i == n { 0.5 } else { 1.0 };
                w * self.absorbed_into(lo + i as f64 * h, 0.0, f64::INFINITY)
            })
            .sum::<f64>()
            * h
    }

    /// Floats held at render time (matrix, both cumulative tables, grids, diagonal).
    pub fn floats_at_render_time(&self) -> usize {
        self.p.len()
            + self.col_cdf.len()
            + self.row_cdf.len()
            + self.lambda_i.len()
            + self.lambda_o.len()
            + 2 * self.diagonal.len()
    }
}

/// λo step of the trapezoid in [`MatrixModel::total_reradiation`], nm.
const TOTAL_STEP_NM: f64 = 0.25;

/// Piecewise-linear interpolation held constant beyond the ends.
pub(crate) fn interp_clamped(x: &[f64], y: &[f64], at: f64) -> f64 {
    interp_indexed(x, GridIndex::IRREGULAR, y, at)
}

/// [`interp_clamped`] with the grid's [`GridIndex`] (built once for `x`).
pub(crate) fn interp_indexed(x: &[f64], index: GridIndex, y: &[f64], at: f64) -> f64 {
    let n = x.len();
    if n == 0 || !at.is_finite() {
        return 0.0;
    }
    if at <= x[0] {
        return y[0];
    }
    if at >= x[n - 1] {
        return y[n - 1];
    }
    locate(x, index, at).map_or(0.0, |(j, t)| (1.0 - t) * y[j] + t * y[j + 1])
}

impl fmt::Display for MatrixModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let r = |o: Option<(f64, f64)>| o.map_or("none".to_string(), |(a, b)| format!("[{a}, {b}] nm"));
        write!(
            f,
            "MatrixModel[source = \"{}\", lambda_i = {}..{} nm ({}), lambda_o = {}..{} nm ({}), excitation = {}, emission = {}]",
            self.source,
            self.lambda_i[0],
            self.lambda_i[self.lambda_i.len() - 1],
            self.lambda_i.len(),
            self.lambda_o[0],
            self.lambda_o[self.lambda_o.len() - 1],
            self.lambda_o.len(),
            r(self.excitation_range),
            r(self.emission_range)
        )
    }
}

lambertian_measured!(MatrixModel);

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::testutil::simpson;

    /// A small synthetic BFC text: λi 300..380 step 20 (5), λo 340..380 step 20 (3).
    pub(crate) fn tiny_bfc() -> String {
        let mut s = String::from("VEC_01\t1\nBFC-450 Matrix File\n");
        for i in 0..8 {
            s.push_str(&format!(";comment {i}\n"));
        }
        s.push_str("340\t380\t20\t5\t300\t20\n");
        s.push_str("r:c:\t300\t320\t340\t360\t380\n");
        s.push_str("340\t0.01\t0.02\t0.5\t-0.001\t0.003\n");
        s.push('\n'); // blank line inside the data, as in some measured files
        s.push_str("360\t0.03\t0.04\t0.01\t0.6\t0.002\n");
        s.push_str("380\t0.02\t0.05\t0.02\t-0.01\t0.7\nEOD\n");
        s
    }

    #[test]
    fn bfc_parses_and_filters() {
        let d = parse_bfc(&tiny_bfc(), "tiny").unwrap();
        assert_eq!(d.lambda_i, vec![300.0, 320.0, 340.0, 360.0, 380.0]);
        assert_eq!(d.lambda_o, vec![340.0, 360.0, 380.0]);
        assert_eq!(d.at(1, 3), 0.6);
        let f = Filtered::new(&d).unwrap();
        assert_eq!(f.diagonal_nm, vec![340.0, 360.0, 380.0]);
        assert_eq!(f.diagonal, vec![0.5, 0.6, 0.7]);
        // below the diagonal (λo 340 < λi 360, 380) -> 0; negative above -> 0
        assert_eq!(f.off[3], 0.0);
        assert_eq!(f.off[4], 0.0);
        assert_eq!(f.off[2 * 5 + 3], 0.0); // (380, 360) = -0.01
        assert_eq!(f.off[2 * 5 + 2], 0.02);
        assert_eq!(f.band_nm, vec![20.0; 3]);
    }

    #[test]
    fn malformed_files_give_clear_errors() {
        let good = tiny_bfc();
        let lines: Vec<&str> = good.lines().collect();
        let cases: Vec<(String, &str)> = vec![
            (lines[..14].join("\n"), "truncated"),
            (good.replace("EOD\n", ""), "EOD"),
            (good.replace("0.04", "NaN"), "line 15, column 3"),
            (good.replace("0.04", "nan"), "not a finite number"),
            (good.replace("0.04", "x1"), "not a number"),
            (good.replace("BFC-450 Matrix File", "Something else"), "wrong header"),
            (good.replace(";comment 3", "oops"), "line 6: wrong header"),
            (good.replace("r:c:\t300", "r:c:\t305"), "expected 300"),
            (good.replace("360\t0.03", "365\t0.03"), "emission wavelength 365"),
            (good.replace("\t0.003\n", "\n"), "line 13: 5 values"),
            (good.replace("340\t380\t20\t5", "340\t380\t20"), "expected 6 numbers"),
            (good.replace("EOD", "400\t1\t1\t1\t1\t1\nEOD"), "expected \"EOD\""),
            (String::new(), "truncated"),
        ];
        for (text, needle) in cases {
            let e = parse_bfc(&text, "bad.BFC").unwrap_err().to_string();
            assert!(e.contains(needle) && e.contains("bad.BFC"), "{needle}: {e}");
        }
        for (text, needle) in [
            ("x,300,310\n380,1,2\n", "wrong header"),
            ("lambda_o\\lambda_i,300,310\n380,1\n", "truncated"),
            ("lambda_o\\lambda_i,300,310\n380,1,NaN\n", "line 2, column 3"),
            ("lambda_o\\lambda_i,300,310\n", "lambda_o grid has 0"),
        ] {
            let e = parse_csv(text, "bad.csv").unwrap_err().to_string();
            assert!(e.contains(needle), "{needle}: {e}");
        }
        let e = load_matrix("/no/such/file.BFC").unwrap_err().to_string();
        assert!(e.contains("/no/such/file.BFC"), "{e}");
        let e = load_matrix("/tmp/x.txt").unwrap_err().to_string();
        assert!(e.contains("filename") && e.contains(".bfc"), "{e}");
    }

    #[test]
    fn exr_round_trip() {
        let d = parse_bfc(&tiny_bfc(), "tiny").unwrap();
        let dir = std::env::temp_dir().join(format!("fluo_exr_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("tiny.exr");
        write_exr(&d, &path).unwrap();
        let back = load_matrix(&path).unwrap();
        let (a, b) = (Filtered::new(&d).unwrap(), Filtered::new(&back).unwrap());
        // The EXR grid is the union of the wavelengths that have channels.
        assert_eq!(b.diagonal_nm, a.diagonal_nm);
        for (x, y) in a.diagonal.iter().zip(&b.diagonal) {
            assert!((x - y).abs() < 1e-7);
        }
        let (ma, mb) = (MatrixModel::new(&a).unwrap(), MatrixModel::new(&b).unwrap());
        for li in [300.0, 310.0, 320.0, 345.0] {
            for lo in [340.0, 350.0, 370.0, 380.0] {
                assert!((ma.reradiation(li, lo) - mb.reradiation(li, lo)).abs() < 1e-8, "{li} {lo}");
            }
        }
        // A malformed spectral channel name is reported.
        use exr::prelude::{
            AnyChannel, AnyChannels, Encoding, FlatSamples, Image, Layer, LayerAttributes, SmallVec, WritableImage,
        };
        let list: SmallVec<[AnyChannel<FlatSamples>; 4]> =
            SmallVec::from_vec(vec![AnyChannel::new("T.abcnm", FlatSamples::F32(vec![0.5]))]);
        let layer = Layer::new((1, 1), LayerAttributes::named(""), Encoding::UNCOMPRESSED, AnyChannels::sort(list));
        let bad = dir.join("bad.exr");
        Image::from_layer(layer).write().to_file(&bad).unwrap();
        let e = load_matrix(&bad).unwrap_err().to_string();
        assert!(e.contains("T.abcnm"), "{e}");
        std::fs::write(dir.join("junk.exr"), b"not an exr").unwrap();
        assert!(load_matrix(dir.join("junk.exr")).unwrap_err().to_string().contains("junk.exr"));
        std::fs::remove_dir_all(&dir).ok();
    }

    fn tiny_model() -> MatrixModel {
        MatrixModel::new(&Filtered::new(&parse_bfc(&tiny_bfc(), "tiny").unwrap()).unwrap()).unwrap()
    }

    #[test]
    fn interpolation_is_energy_per_nm() {
        let m = tiny_model();
        // node value: D / Δλo
        assert!((m.reradiation(300.0, 360.0) - 0.03 / 20.0).abs() < 1e-15);
        assert_eq!(m.reradiation(360.0, 340.0), 0.0);
        assert_eq!(m.reradiation(290.0, 360.0), 0.0);
        // bilinear between nodes
        let want = 0.25 * (0.03 + 0.04 + 0.02 + 0.05) / 20.0;
        assert!((m.reradiation(310.0, 370.0) - want).abs() < 1e-15);
        assert!((m.reflectance(350.0) - 0.55).abs() < 1e-15);
        assert_eq!(m.reflectance(300.0), 0.5); // held constant below the first node
    }

    #[test]
    fn tabulated_integrals_match_quadrature() {
        let m = tiny_model();
        for lo in [340.0, 351.0, 365.5, 380.0] {
            let q = simpson(|li| m.reradiation(li, lo), 300.0, lo, 20_000);
            let a = m.absorbed_into(lo, 0.0, 1000.0);
            assert!((a - q).abs() < 1e-7, "λo {lo}: {a} vs {q}");
            let q = simpson(|li| m.reradiation(li, lo), 305.0, 330.0_f64.min(lo), 20_000);
            assert!((m.absorbed_into(lo, 305.0, 330.0) - q).abs() < 1e-7);
        }
        for li in [300.0_f64, 311.0, 345.0, 379.0] {
            let q = simpson(|lo| m.reradiation(li, lo), li.max(340.0), 380.0, 20_000);
            assert!((m.reradiated_albedo(li) - q).abs() < 1e-7, "λi {li}");
        }
    }

    #[test]
    fn sampling_inverts_the_cdf_exactly() {
        let m = tiny_model();
        for li in [300.0, 313.0, 350.0] {
            let total = m.reradiated_albedo(li);
            for xi in [0.0, 0.1, 0.37, 0.5, 0.9, 1.0] {
                let (lo, pdf) = m.sample_emission(li, xi).unwrap();
                let c = simpson(|x| m.reradiation(li, x), li.max(340.0), lo, 4000) / total;
                assert!((c - xi).abs() < 1e-6, "λi {li} ξ {xi}: cdf {c}");
                assert!((pdf - m.emission_pdf(li, lo)).abs() < 1e-12 * pdf.max(1.0));
            }
        }
        for (lo, range) in [(380.0, (300.0, 830.0)), (365.0, (310.0, 330.0)), (341.0, (300.0, 400.0))] {
            let total = m.absorbed_into(lo, range.0, range.1);
            for xi in [0.0, 0.2, 0.5, 0.99] {
                let (li, pdf) = m.sample_excitation(lo, xi, range.0, range.1).unwrap();
                assert!(li >= range.0 && li <= range.1.min(lo));
                let c = simpson(|x| m.reradiation(x, lo), range.0, li, 4000) / total;
                assert!((c - xi).abs() < 1e-6, "λo {lo} ξ {xi}: cdf {c}");
                assert!((pdf - m.excitation_pdf(lo, li, range.0, range.1)).abs() < 1e-12 * pdf.max(1.0));
            }
        }
        assert!(m.sample_excitation(330.0, 0.5, 300.0, 830.0).is_none()); // below the λo grid
        assert!(m.sample_excitation(360.0, 0.5, 370.0, 830.0).is_none()); // range above λo
    }

    #[test]
    fn every_shared_file_loads() {
        let files = shared_bispectral_files();
        if files.is_empty() {
            eprintln!("skipping: shared data not found (set FLUO_SHARED_DATA or place shared/ beside the repo)");
            return;
        }
        assert_eq!(files.len(), 6, "{files:?}");
        for f in files {
            let m = MatrixModel::from_file(&f).unwrap();
            assert_eq!(m.lambda_i().len(), 49, "{}", f.display());
            assert_eq!(m.lambda_o().len(), 41);
            assert_eq!(m.diagonal().0.len(), 41);
            // 10 nm grids: indexed directly
            assert!(m.index_i.is_uniform() && m.index_o.is_uniform() && m.index_diagonal.is_uniform());
            assert!(m.is_fluorescent(), "{}", f.display());
            // the reradiated albedo never exceeds one (per excitation wavelength)
            for li in (300..=780).step_by(5) {
                let a = m.reradiated_albedo(li as f64) + if li >= 380 { m.reflectance(li as f64) } else { 0.0 };
                assert!(a.is_finite() && a < 1.2, "{}: λi {li}: {a}", f.display());
            }
        }
    }
}
