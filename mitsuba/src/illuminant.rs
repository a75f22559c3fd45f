//! fluo_illuminant: an emission spectrum (a CIE illuminant or a CSV file).

use super::*;

/// Opaque emission spectrum for `fluo_illuminant`.
pub struct Illuminant {
    label: String,
    pub(crate) spectrum: IrregularSpectrum,
}

pub(crate) fn illuminant_new(
    name: &str,
    filename: &str,
    scale: f64,
    normalize: bool,
) -> Result<Box<Illuminant>, String> {
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
pub(crate) fn illuminant_nodes(s: &Illuminant, wavelengths: &mut Vec<f64>, values: &mut Vec<f64>) {
    wavelengths.clear();
    wavelengths.extend_from_slice(s.spectrum.wavelengths_nm());
    values.clear();
    values.extend_from_slice(s.spectrum.values());
}

pub(crate) fn illuminant_range(s: &Illuminant) -> Range {
    let w = s.spectrum.wavelengths_nm();
    Range { lo: w.first().copied().unwrap_or(0.0), hi: w.last().copied().unwrap_or(0.0) }
}

pub(crate) fn illuminant_mean(s: &Illuminant) -> f64 {
    s.spectrum.integrate_product(&|_: f64| 1.0, CIE_MIN_NM, CIE_MAX_NM, 1.0).unwrap_or(0.0) / (CIE_MAX_NM - CIE_MIN_NM)
}

pub(crate) fn illuminant_srgb(s: &Illuminant) -> Rgb {
    // Out-of-gamut (negative) channels clipped, as an sRGB film must store them: a violet
    // or UV lamp has negative linear-sRGB green, which Mitsuba reports per sample as an
    // invalid value.
    rgb(spectrum_to_srgb(|l| s.spectrum.eval(l)).map(|v| v.max(0.0)))
}

pub(crate) fn illuminant_to_string(s: &Illuminant) -> String {
    let r = illuminant_range(s);
    format!("{} ({}-{} nm)", s.label, r.lo, r.hi)
}

/// Wavelength below which light counts as ultraviolet for [`illuminant_is_mostly_uv`], nm.
pub(crate) const UV_EDGE_NM: f64 = 400.0;

pub(crate) fn illuminant_is_mostly_uv(s: &Illuminant) -> bool {
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
