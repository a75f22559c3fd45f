//! Helpers shared by the unit tests of the models (compiled for tests only).

/// Composite Simpson on [a, b] with n (even) intervals.
pub fn simpson(f: impl Fn(f64) -> f64, a: f64, b: f64, n: usize) -> f64 {
    let h = (b - a) / n as f64;
    let mut s = f(a) + f(b);
    for i in 1..n {
        s += if i % 2 == 1 { 4.0 } else { 2.0 } * f(a + i as f64 * h);
    }
    s * h / 3.0
}

/// A deterministic stream of uniforms in [0, 1) (SplitMix64).
pub fn uniforms(n: usize, seed: u64) -> Vec<f64> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            (z >> 11) as f64 / (1u64 << 53) as f64
        })
        .collect()
}

/// Pearson chi-square statistic of samples on [lo, hi] against a density, with `bins`
/// equal bins; bins whose expected count is below 5 are pooled with the next. Samples
/// must lie in [lo, hi] (up to 1e-9 of its width). Returns (statistic, degrees of freedom).
pub fn chi2(samples: &[f64], lo: f64, hi: f64, bins: usize, pdf: impl Fn(f64) -> f64) -> (f64, usize) {
    let slack = 1e-9 * (hi - lo);
    let mut obs = vec![0.0; bins];
    for &x in samples {
        assert!(x >= lo - slack && x <= hi + slack, "sample {x} outside [{lo}, {hi}]");
        let b = (((x - lo) / (hi - lo)) * bins as f64).floor().clamp(0.0, bins as f64 - 1.0);
        obs[b as usize] += 1.0;
    }
    let n = samples.len() as f64;
    let w = (hi - lo) / bins as f64;
    let (mut stat, mut dof, mut po, mut pe) = (0.0, 0usize, 0.0, 0.0);
    for (i, o) in obs.iter().enumerate() {
        po += o;
        pe += n * simpson(&pdf, lo + i as f64 * w, lo + (i + 1) as f64 * w, 64);
        if pe >= 5.0 {
            stat += (po - pe).powi(2) / pe;
            dof += 1;
            po = 0.0;
            pe = 0.0;
        }
    }
    (stat, dof.saturating_sub(1))
}

/// Upper 1e-4 quantile of chi-square with `dof` degrees of freedom (Wilson–Hilferty).
pub fn chi2_critical(dof: usize) -> f64 {
    let k = dof.max(1) as f64;
    k * (1.0 - 2.0 / (9.0 * k) + 3.719 * (2.0 / (9.0 * k)).sqrt()).powi(3)
}

/// A green `fluo_jung` dye (520 nm, 60 nm Stokes shift, c = 0.8, Q = 0.9).
pub fn green_dye() -> crate::models::jung::JungFluorescence {
    crate::models::jung::JungFluorescence::new(crate::models::jung::JungParams {
        emission_peak: 520.0,
        stokes_shift: 60.0,
        concentration: 0.8,
        quantum_yield: 0.9,
    })
    .expect("valid parameters")
}
