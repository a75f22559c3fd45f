//! The offline optimiser: fits the coefficients of every node of an RGB cube (Jung et
//! al. 2019, sec. 3.2–3.4) under the model of the [module docs](super) and returns the
//! [`Cube`] that [`Cube::save`] writes. Renders never run it.
//!
//! # Objective (sec. 3.2, 3.4)
//! Per cube entry with target RGB t, Levenberg–Marquardt minimises the squared norm of
//! the residual `(RGB(c) − t, 100·max(0, |r'(λ₁)| − τ))`: the RGB distance plus the
//! smoothness penalty of sec. 3.2 (here squared, as least squares needs; it is zero
//! exactly where the paper's is) with threshold τ (`threshold`, ∞ disables it,
//! [`SMOOTH_THRESHOLD_PER_NM`] = 0.016 nm⁻¹ is the paper's Macbeth bound). |r'(λ₁)| is
//! the paper's estimate of the steepest slope: the extremes of r on the visible range
//! (the ends and the polynomial's vertex), the midpoint of their sigmoid values mapped
//! back through S⁻¹, and the slope where P crosses it.
//!
//! # Strategy (sec. 3.4, Algorithm 1)
//! 1. Reflectance-only solve for every entry (c = 0), then neighbour propagation
//!    sweeps: an entry with remaining error restarts from the best of its 26
//!    neighbours' coefficients ([`STAGE1_SWEEPS`] at most).
//! 2. Entries still above [`FLUORESCENCE_TRIGGER`]: brute-force initialisation of c^f
//!    with c^r fixed, over λe ∈ [300, 800] nm (10 nm steps), s ∈ [5, 95] nm (10 nm),
//!    c ∈ {0.1, …, 1} (sec. 4); then alternating joint / reflectance-only solves.
//! 3. `rounds` rounds of neighbour propagation: each entry with remaining error
//!    restarts the alternating solves from the best two of its own and its 26
//!    neighbours' coefficients (by their error at this entry); the best coefficients
//!    found so far are always kept.
//!
//! Every stage reads the previous state and writes a new one (Jacobi updates), and
//! entries are split over threads in fixed chunks, so a cube is bit-for-bit identical
//! for any thread count.
//!
//! # Numerics
//! Parameters are the normalised reflectance coefficients and λe, s in units of 100 nm
//! (see the module docs). Jacobians are forward differences; bounds are enforced by
//! projection.

use super::colour_system::{table, table1, ColourSystem, Fluo};
use super::cube::{grid_rgb, Cube, CubeHeader, Entry, MAX_RESOLUTION};
use super::{from_nm, poly, to_nm, Coefficients, Params, LAMBDA_MIN_NM, QUANTUM_YIELD, T_SPAN};
use crate::colour::RgbSpace;
use crate::sigmoid::{sigmoid, sigmoid_derivative};
use crate::{Error, Result};

/// Weight of the smoothness penalty (sec. 3.2).
pub const PENALTY_WEIGHT: f64 = 100.0;
/// The paper's smoothness threshold: steepest slope of the Macbeth chart, nm⁻¹.
pub const SMOOTH_THRESHOLD_PER_NM: f64 = 0.016;
/// Bounds of the emission peak λe during optimisation, nm (sec. 4).
pub const EMISSION_PEAK_BOUNDS_NM: (f64, f64) = (300.0, 800.0);
/// Bounds of the Stokes shift s during optimisation, nm (brute force covers 5–95).
pub const STOKES_SHIFT_BOUNDS_NM: (f64, f64) = (5.0, 150.0);
/// Bound on |normalised reflectance coefficient| (box-like spectra need large ones).
pub const REFLECTANCE_COEFF_LIMIT: f64 = 1e5;
/// Entries whose RGB distance after the reflectance-only stage exceeds this get a
/// fluorescent component; below it, c stays exactly 0.
pub const FLUORESCENCE_TRIGGER: f64 = 1e-3;
/// RGB distance above which an entry counts as having "remaining error" in reports.
pub const REMAINING_ERROR: f64 = 1e-3;
/// LM stops once the residual norm is below this.
const LM_TARGET: f64 = 1e-7;
/// Levenberg–Marquardt iteration bound per solve.
const LM_MAX_ITERATIONS: usize = 60;
/// Damping bounds of Levenberg–Marquardt (give up above the upper one).
const LM_DAMPING_RANGE: (f64, f64) = (1e-12, 1e10);
/// Reflectance-only neighbour sweeps at most.
pub const STAGE1_SWEEPS: usize = 40;
/// Alternating joint / reflectance-only solves after the brute-force initialisation.
const INITIAL_ALTERNATIONS: usize = 6;
/// Alternating solves per seed in each propagation round.
const ROUND_ALTERNATIONS: usize = 4;
/// Seeds (own + neighbours, best first) tried per entry in each round.
const ROUND_SEEDS: usize = 2;
/// A sweep or round counts an entry as improved when its cost drops below this
/// fraction of the previous cost; generation stops when none improves.
const SIGNIFICANT_IMPROVEMENT: f64 = 0.98;

/// Lower and upper bounds of the optimiser parameters.
const LOWER: Params = [
    -REFLECTANCE_COEFF_LIMIT,
    -REFLECTANCE_COEFF_LIMIT,
    -REFLECTANCE_COEFF_LIMIT,
    EMISSION_PEAK_BOUNDS_NM.0 / 100.0,
    0.0,
    STOKES_SHIFT_BOUNDS_NM.0 / 100.0,
];
const UPPER: Params = [
    REFLECTANCE_COEFF_LIMIT,
    REFLECTANCE_COEFF_LIMIT,
    REFLECTANCE_COEFF_LIMIT,
    EMISSION_PEAK_BOUNDS_NM.1 / 100.0,
    1.0,
    STOKES_SHIFT_BOUNDS_NM.1 / 100.0,
];

/// Optimiser parameters → coefficients (reflectance in the nm domain).
fn coefficients_of(p: &Params) -> Coefficients {
    Coefficients { reflectance: to_nm(p), emission_peak: 100.0 * p[3], concentration: p[4], stokes_shift: 100.0 * p[5] }
}

/// The paper's approximate steepest slope |r'(λ₁)| of the reflectance, nm⁻¹ (sec. 3.2).
pub fn max_slope(reflectance_nm: &[f64; 3]) -> f64 {
    let t = from_nm(reflectance_nm);
    max_slope_params(&[t[0], t[1], t[2], 0.0, 0.0, 0.0])
}

fn max_slope_params(p: &Params) -> f64 {
    let (a, b) = (p[0], p[1]);
    let mut lo = poly(p, 0.0).min(poly(p, 1.0));
    let mut hi = poly(p, 0.0).max(poly(p, 1.0));
    if a != 0.0 {
        let t_ext = -b / (2.0 * a);
        if t_ext > 0.0 && t_ext < 1.0 {
            let v = poly(p, t_ext);
            lo = lo.min(v);
            hi = hi.max(v);
        }
    }
    // y_mid = S⁻¹((S(hi) + S(lo))/2), S⁻¹(y) = (2y − 1)/(2 sqrt(y(1 − y))).
    let y = 0.5 * (sigmoid(hi) + sigmoid(lo));
    let q = y * (1.0 - y);
    if !(q > 0.0) {
        return 0.0;
    }
    let y_mid = (2.0 * y - 1.0) / (2.0 * q.sqrt());
    // Solve a t² + b t + (c − y_mid) = 0 for a root, preferring one in [0, 1].
    let c = p[2] - y_mid;
    let roots: Vec<f64> = if a.abs() < 1e-300 {
        if b != 0.0 {
            vec![-c / b]
        } else {
            vec![]
        }
    } else {
        let disc = b * b - 4.0 * a * c;
        if disc < 0.0 {
            vec![-b / (2.0 * a)]
        } else {
            // Numerically stable pair of roots.
            let q = -0.5 * (b + b.signum() * disc.sqrt());
            let mut r = vec![];
            if q != 0.0 {
                r.push(c / q);
            }
            r.push(q / a);
            r
        }
    };
    let t1 =
        roots.iter().copied().filter(|t| t.is_finite()).min_by(|x, y| dist01(*x).total_cmp(&dist01(*y))).unwrap_or(0.5);
    let slope_t = sigmoid_derivative(poly(p, t1)) * (2.0 * a * t1 + b);
    (slope_t / T_SPAN).abs()
}

fn dist01(t: f64) -> f64 {
    if t < 0.0 {
        -t
    } else if t > 1.0 {
        t - 1.0
    } else {
        0.0
    }
}

/// One entry's least-squares problem.
struct Problem<'a> {
    sys: &'a ColourSystem,
    target: [f64; 3],
    threshold: f64,
}

impl Problem<'_> {
    fn residuals(&self, p: &Params) -> [f64; 4] {
        let rgb = self.sys.rgb_params(p);
        let pen = if self.threshold.is_finite() {
            PENALTY_WEIGHT * (max_slope_params(p) - self.threshold).max(0.0)
        } else {
            0.0
        };
        [rgb[0] - self.target[0], rgb[1] - self.target[1], rgb[2] - self.target[2], pen]
    }

    fn cost(&self, p: &Params) -> f64 {
        let r = self.residuals(p);
        r.iter().map(|x| x * x).sum()
    }

    /// RGB distance (no penalty).
    fn rgb_error(&self, p: &Params) -> f64 {
        let r = self.residuals(p);
        (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt()
    }

    /// Bounded Levenberg–Marquardt over the parameters marked `free`.
    fn solve(&self, p0: Params, free: [bool; 6]) -> (Params, f64) {
        let idx: Vec<usize> = (0..6).filter(|&i| free[i]).collect();
        let n = idx.len();
        let mut p = p0;
        for i in 0..6 {
            p[i] = p[i].clamp(LOWER[i], UPPER[i]);
        }
        let mut r = self.residuals(&p);
        let mut cost: f64 = r.iter().map(|x| x * x).sum();
        let mut mu = 1e-3;
        for _ in 0..LM_MAX_ITERATIONS {
            if !cost.is_finite() || cost.sqrt() < LM_TARGET {
                break;
            }
            // Forward-difference Jacobian (4 × n).
            let mut jac = [[0.0; 6]; 4];
            for (col, &i) in idx.iter().enumerate() {
                let h = 1e-7 * p[i].abs().max(1.0);
                let mut q = p;
                q[i] += h;
                let rq = self.residuals(&q);
                for row in 0..4 {
                    jac[row][col] = (rq[row] - r[row]) / h;
                }
            }
            let mut jtj = [[0.0; 6]; 6];
            let mut jtr = [0.0; 6];
            for a in 0..n {
                for b in 0..n {
                    jtj[a][b] = (0..4).map(|row| jac[row][a] * jac[row][b]).sum();
                }
                jtr[a] = (0..4).map(|row| jac[row][a] * r[row]).sum();
            }
            let mut improved = false;
            while mu < LM_DAMPING_RANGE.1 {
                let mut m = jtj;
                for a in 0..n {
                    m[a][a] += mu * (jtj[a][a] + 1e-9);
                }
                let Some(delta) = solve_linear(&mut m, jtr.map(|x| -x), n) else {
                    mu *= 10.0;
                    continue;
                };
                let mut q = p;
                for (col, &i) in idx.iter().enumerate() {
                    q[i] = (q[i] + delta[col]).clamp(LOWER[i], UPPER[i]);
                }
                let rq = self.residuals(&q);
                let cq: f64 = rq.iter().map(|x| x * x).sum();
                if cq.is_finite() && cq < cost {
                    let rel = (cost - cq) / cost;
                    p = q;
                    r = rq;
                    cost = cq;
                    mu = (mu * 0.3).max(LM_DAMPING_RANGE.0);
                    improved = rel > 1e-10;
                    break;
                }
                mu *= 4.0;
            }
            if !improved {
                break;
            }
        }
        (p, cost)
    }

    /// Alternate joint and reflectance-only solves, keeping the best.
    fn alternate(&self, p0: Params, steps: usize) -> (Params, f64) {
        let mut best = (p0, self.cost(&p0));
        let mut p = p0;
        for l in 0..steps {
            if best.1.sqrt() < LM_TARGET {
                break;
            }
            let free = if l % 2 == 0 { [true; 6] } else { [true, true, true, false, false, false] };
            let (q, c) = self.solve(p, free);
            p = q;
            if c < best.1 {
                best = (q, c);
            }
        }
        best
    }
}

/// Solve the n × n system `m x = rhs` by Gaussian elimination with partial pivoting.
fn solve_linear(m: &mut [[f64; 6]; 6], mut rhs: [f64; 6], n: usize) -> Option<[f64; 6]> {
    for col in 0..n {
        let piv = (col..n).max_by(|&a, &b| m[a][col].abs().total_cmp(&m[b][col].abs()))?;
        if !(m[piv][col].abs() > 1e-300) {
            return None;
        }
        m.swap(col, piv);
        rhs.swap(col, piv);
        for row in col + 1..n {
            let f = m[row][col] / m[col][col];
            let pivot_row = m[col];
            for (target, pivot) in m[row][col..n].iter_mut().zip(&pivot_row[col..n]) {
                *target -= f * pivot;
            }
            rhs[row] -= f * rhs[col];
        }
    }
    let mut x = [0.0; 6];
    for row in (0..n).rev() {
        let s: f64 = (row + 1..n).map(|k| m[row][k] * x[k]).sum();
        x[row] = (rhs[row] - s) / m[row][row];
    }
    x.iter().take(n).all(|v| v.is_finite()).then_some(x)
}

/// Settings of a cube generation.
#[derive(Debug, Clone)]
pub struct CubeSettings {
    /// Working space of the RGB grid.
    pub space: RgbSpace,
    /// CIE illuminant name (e.g. "D65").
    pub illuminant: String,
    /// Entries per axis (grid k/(n−1)).
    pub resolution: usize,
    /// Smoothness threshold τ, nm⁻¹ (∞: none).
    pub threshold: f64,
    /// Neighbour-propagation rounds of the fluorescent stage (paper: 50).
    pub rounds: usize,
    /// Worker threads (the result does not depend on it).
    pub threads: usize,
}

impl CubeSettings {
    /// Validate the settings.
    pub fn validate(&self) -> Result<()> {
        if !(2..=MAX_RESOLUTION).contains(&self.resolution) {
            return Err(Error::param("resolution", self.resolution, format!("[2, {MAX_RESOLUTION}]")));
        }
        if !(self.threshold > 0.0) {
            return Err(Error::param("threshold", self.threshold, "(0, inf] nm⁻¹ (\"inf\" disables the penalty)"));
        }
        if self.threads == 0 {
            return Err(Error::param("threads", 0, "at least 1"));
        }
        Ok(())
    }
}

/// Indices of the up to 26 neighbours of `index`.
fn neighbours(n: usize, index: usize) -> Vec<usize> {
    let (i, j, k) = ((index / (n * n)) as isize, ((index / n) % n) as isize, (index % n) as isize);
    let mut out = Vec::with_capacity(26);
    for di in -1..=1 {
        for dj in -1..=1 {
            for dk in -1..=1 {
                if di == 0 && dj == 0 && dk == 0 {
                    continue;
                }
                let (a, b, c) = (i + di, j + dj, k + dk);
                let lim = n as isize;
                if a >= 0 && a < lim && b >= 0 && b < lim && c >= 0 && c < lim {
                    out.push(((a * lim + b) * lim + c) as usize);
                }
            }
        }
    }
    out
}

/// Run `f` over `items` on `threads` threads; results in item order. Threads take
/// small chunks from a shared counter (load balancing), and every result depends only
/// on its item, so the output is identical for any thread count.
fn par_map<T: Sync, R: Send>(items: &[T], threads: usize, f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    if items.is_empty() {
        return Vec::new();
    }
    let chunk = items.len().div_ceil(threads.max(1) * 16).max(1);
    let chunks: Vec<&[T]> = items.chunks(chunk).collect();
    let next = AtomicUsize::new(0);
    let mut done: Vec<(usize, Vec<R>)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..threads.max(1))
            .map(|_| {
                scope.spawn(|| {
                    let mut out = Vec::new();
                    loop {
                        let c = next.fetch_add(1, Ordering::Relaxed);
                        let Some(items) = chunks.get(c) else { break };
                        out.push((c, items.iter().map(&f).collect::<Vec<R>>()));
                    }
                    out
                })
            })
            .collect();
        handles.into_iter().flat_map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))).collect()
    });
    done.sort_by_key(|(c, _)| *c);
    done.into_iter().flat_map(|(_, v)| v).collect()
}

/// Work state of one entry during generation.
#[derive(Clone, Copy)]
struct State {
    p: Params,
    cost: f64,
}

/// Brute-force grid of the fluorescence initialisation (sec. 4).
/// One brute-force model: λe, s, emission RGB per unit absorbed power, and its
/// absorption nodes (λ, weight, RGB).
type BruteForceModel = (f64, f64, [f64; 3], Vec<(f64, f64, [f64; 3])>);

struct BruteForce {
    /// (λe, s) with precomputed emission RGB (per unit absorbed power) and nodes.
    models: Vec<BruteForceModel>,
}

impl BruteForce {
    fn new(sys: &ColourSystem) -> Self {
        let mut models = Vec::new();
        for ie in 0..=50 {
            let le = 300.0 + 10.0 * ie as f64;
            for is in 0..10 {
                let s = 5.0 + 10.0 * is as f64;
                let Some(f) = Fluo::new(le, s) else { continue };
                let mut emitted = [0.0; 3];
                for (l, wt) in f.emission_nodes() {
                    let cm = table(&sys.cmf_rgb, l);
                    for ch in 0..3 {
                        emitted[ch] += wt * cm[ch];
                    }
                }
                // Absorption nodes with the illuminant folded in: (t, wt·I, cmf_rgb).
                let nodes: Vec<(f64, f64, [f64; 3])> = f
                    .absorption_nodes()
                    .filter_map(|(l, wt)| {
                        let i = table1(&sys.illum, l);
                        (i > 0.0).then(|| ((l - LAMBDA_MIN_NM) / T_SPAN, wt * i, table(&sys.cmf_rgb, l)))
                    })
                    .collect();
                if !nodes.is_empty() {
                    models.push((le, s, emitted, nodes));
                }
            }
        }
        Self { models }
    }

    /// Best (λe, c, s) for fixed reflectance parameters.
    fn search(&self, prob: &Problem, p: &Params) -> Params {
        let base = prob.sys.rgb_params(&[p[0], p[1], p[2], 5.0, 0.0, 0.5]);
        let mut best = (f64::INFINITY, *p);
        for (le, s, emitted, nodes) in &self.models {
            let (mut absorbed, mut lost) = (0.0, [0.0; 3]);
            for (t, wt, cm) in nodes {
                absorbed += wt;
                let r = sigmoid(poly(p, *t));
                for ch in 0..3 {
                    lost[ch] += r * wt * cm[ch];
                }
            }
            for ic in 1..=10 {
                let c = 0.1 * ic as f64;
                let mut d2 = 0.0;
                for ch in 0..3 {
                    let v = base[ch] + c * (QUANTUM_YIELD * absorbed * emitted[ch] - lost[ch]) - prob.target[ch];
                    d2 += v * v;
                }
                if d2 < best.0 {
                    best = (d2, [p[0], p[1], p[2], le / 100.0, c, s / 100.0]);
                }
            }
        }
        best.1
    }
}

/// Statistics of a generation, for the log.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct GenerationStats {
    /// Entries with remaining error after the reflectance-only stage.
    pub needing_fluorescence: usize,
    /// Entries that use fluorescence (c > 0) in the final cube.
    pub fluorescent: usize,
    /// Entries whose final RGB error exceeds [`REMAINING_ERROR`].
    pub remaining: usize,
    /// Wall-clock seconds per stage.
    pub seconds: Vec<(String, f64)>,
}

/// Generate a coefficient cube (see the module docs for the strategy). `log` receives
/// one line per stage.
pub fn generate_cube(settings: &CubeSettings, log: &mut dyn FnMut(&str)) -> Result<(Cube, GenerationStats)> {
    settings.validate()?;
    let sys = ColourSystem::new(settings.space, &settings.illuminant)?;
    let n = settings.resolution;
    let count = n * n * n;
    let threads = settings.threads;
    let threshold = settings.threshold;
    let problem = |i: usize| Problem { sys: &sys, target: grid_rgb(n, i), threshold };
    let mut stats = GenerationStats::default();
    let mut clock = std::time::Instant::now();
    let mut lap = |name: &str, stats: &mut GenerationStats, log: &mut dyn FnMut(&str), msg: String| {
        let s = clock.elapsed().as_secs_f64();
        clock = std::time::Instant::now();
        stats.seconds.push((name.to_string(), s));
        log(&format!("{name}: {msg} ({s:.1} s)"));
    };
    let refl_only = [true, true, true, false, false, false];

    // Stage 1: reflectance only.
    let indices: Vec<usize> = (0..count).collect();
    let mut state: Vec<State> = par_map(&indices, threads, |&i| {
        let prob = problem(i);
        let t = prob.target;
        let y = ((t[0] + t[1] + t[2]) / 3.0).clamp(1e-3, 1.0 - 1e-3);
        let p0 = [0.0, 0.0, (2.0 * y - 1.0) / (2.0 * (y * (1.0 - y)).sqrt()), 5.0, 0.0, 0.5];
        let (p, cost) = prob.solve(p0, refl_only);
        State { p, cost }
    });
    let unsolved = |st: &[State]| -> Vec<usize> {
        (0..count)
            .filter(|&i| {
                problem(i).rgb_error(&st[i].p) > FLUORESCENCE_TRIGGER * 0.1
                    || st[i].cost.sqrt() > FLUORESCENCE_TRIGGER * 0.1
            })
            .collect()
    };
    lap("reflectance solve", &mut stats, log, format!("{} entries", count));
    for sweep in 0..STAGE1_SWEEPS {
        let todo = unsolved(&state);
        if todo.is_empty() {
            break;
        }
        let prev = state.clone();
        let updates = par_map(&todo, threads, |&i| {
            let prob = problem(i);
            let mut seeds: Vec<(f64, Params)> =
                neighbours(n, i).into_iter().map(|k| (prob.cost(&prev[k].p), prev[k].p)).collect();
            seeds.sort_by(|a, b| a.0.total_cmp(&b.0));
            let mut best = prev[i];
            for (c, p) in seeds.into_iter().take(2) {
                if !(c < best.cost * 1e3 || c < 1.0) {
                    continue;
                }
                let (q, cq) = prob.solve(p, refl_only);
                if cq < best.cost {
                    best = State { p: q, cost: cq };
                }
            }
            best
        });
        let changed = keep_improvements(&mut state, &todo, updates);
        log(&format!("  reflectance sweep {sweep}: {} unsolved, {changed} improved", todo.len()));
        if changed == 0 {
            break;
        }
    }
    let stage1: Vec<State> = state.clone();
    let needs: Vec<usize> = (0..count).filter(|&i| stage1[i].cost.sqrt() > FLUORESCENCE_TRIGGER).collect();
    stats.needing_fluorescence = needs.len();
    lap("reflectance sweeps", &mut stats, log, format!("{} entries need fluorescence", needs.len()));

    // Stage 2: brute-force initialisation of c^f, then alternating solves.
    let brute = BruteForce::new(&sys);
    let init = par_map(&needs, threads, |&i| {
        let prob = problem(i);
        let p0 = brute.search(&prob, &stage1[i].p);
        let (p, cost) = prob.alternate(p0, INITIAL_ALTERNATIONS);
        if cost < stage1[i].cost {
            State { p, cost }
        } else {
            stage1[i]
        }
    });
    for (&i, u) in needs.iter().zip(init) {
        state[i] = u;
    }
    let remaining =
        |st: &[State]| needs.iter().copied().filter(|&i| st[i].cost.sqrt() > FLUORESCENCE_TRIGGER).collect::<Vec<_>>();
    lap("fluorescence init", &mut stats, log, format!("{} with remaining error", remaining(&state).len()));

    // Stage 3: neighbour propagation rounds.
    for round in 0..settings.rounds {
        let todo = remaining(&state);
        if todo.is_empty() {
            break;
        }
        let prev = state.clone();
        let updates = par_map(&todo, threads, |&i| {
            let prob = problem(i);
            let mut seeds: Vec<(f64, Params)> =
                std::iter::once(i).chain(neighbours(n, i)).map(|k| (prob.cost(&prev[k].p), prev[k].p)).collect();
            seeds.sort_by(|a, b| a.0.total_cmp(&b.0));
            seeds.dedup_by(|a, b| a.1 == b.1);
            let mut best = prev[i];
            for (_, p) in seeds.into_iter().take(ROUND_SEEDS) {
                let (q, cq) = prob.alternate(p, ROUND_ALTERNATIONS);
                if cq < best.cost {
                    best = State { p: q, cost: cq };
                }
            }
            best
        });
        let changed = keep_improvements(&mut state, &todo, updates);
        log(&format!("  round {round}: {} with remaining error, {changed} improved", todo.len()));
        if changed == 0 {
            break;
        }
    }
    lap("propagation", &mut stats, log, format!("{} with remaining error", remaining(&state).len()));

    // Round to the stored precision first, so the stored errors are those of the file.
    let f32_round = |p: &Params| p.map(|x| f64::from(x as f32));
    let entries: Vec<Entry> = (0..count)
        .map(|i| {
            let prob = problem(i);
            let s1 = f32_round(&stage1[i].p);
            let mut p = f32_round(&state[i].p);
            if p[4] <= 0.0 {
                p[3] = 5.0;
                p[4] = 0.0;
                p[5] = 0.5;
            }
            Entry {
                coefficients: coefficients_of(&p),
                error: prob.rgb_error(&p),
                reflectance_only: to_nm(&s1),
                reflectance_only_error: prob.rgb_error(&s1),
            }
        })
        .collect();
    stats.fluorescent = entries.iter().filter(|e| e.coefficients.concentration > 0.0).count();
    stats.remaining = entries.iter().filter(|e| e.error > REMAINING_ERROR).count();
    let cube = Cube {
        header: CubeHeader { space: settings.space, illuminant: sys.illuminant.clone(), resolution: n, threshold },
        entries,
    };
    Ok((cube, stats))
}

/// Replace each entry of `todo` whose update lowers its cost; returns how many improved
/// significantly (by more than [`SIGNIFICANT_IMPROVEMENT`]).
fn keep_improvements(state: &mut [State], todo: &[usize], updates: Vec<State>) -> usize {
    let mut changed = 0;
    for (&i, u) in todo.iter().zip(updates) {
        if u.cost < state[i].cost {
            changed += usize::from(u.cost < SIGNIFICANT_IMPROVEMENT * state[i].cost);
            state[i] = u;
        }
    }
    changed
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::sigmoid::SigmoidPolynomial;

    #[test]
    fn max_slope_matches_dense_search_for_steep_spectra() {
        // A steep band-pass: the paper's estimate is close to the true maximum slope.
        for c in [[-0.01, 11.0, -3000.0], [0.0, 0.2, -100.0], [0.0, -0.05, 25.0]] {
            let s = SigmoidPolynomial::new(c).unwrap();
            let dense = (0..=47000).map(|i| s.derivative(360.0 + i as f64 * 0.01).abs()).fold(0.0, f64::max);
            let est = max_slope(&c);
            assert!((est - dense).abs() < 0.05 * dense, "{c:?}: {est} vs {dense}");
        }
        // constant spectrum: zero slope
        assert_eq!(max_slope(&[0.0, 0.0, 1.0]), 0.0);
    }

    #[test]
    fn lm_reaches_in_gamut_colours_exactly() {
        let sys = ColourSystem::new(RgbSpace::Srgb, "D65").unwrap();
        for target in [[0.5, 0.5, 0.5], [0.8, 0.3, 0.2], [0.1, 0.6, 0.3]] {
            let prob = Problem { sys: &sys, target, threshold: f64::INFINITY };
            let (p, cost) = prob.solve([0.0; 6], [true, true, true, false, false, false]);
            assert!(cost.sqrt() < 1e-6, "{target:?}: {}", cost.sqrt());
            assert_eq!(p[4], 0.0);
        }
    }

    #[test]
    fn small_cube_is_deterministic_and_entries_reproduce_colours() {
        let settings = CubeSettings {
            space: RgbSpace::AcesCg,
            illuminant: "D65".into(),
            resolution: 5,
            threshold: f64::INFINITY,
            rounds: 3,
            threads: 2,
        };
        let (cube, stats) = generate_cube(&settings, &mut |_| {}).unwrap();
        let (cube1, _) = generate_cube(&CubeSettings { threads: 1, ..settings.clone() }, &mut |_| {}).unwrap();
        assert_eq!(cube.to_bytes(), cube1.to_bytes(), "thread count changed the cube");
        assert!(stats.needing_fluorescence > 0 && stats.fluorescent > 0, "{stats:?}");
        let q = cube.quantised().unwrap();
        let sys = q.colour_system().unwrap();
        // A sample of entries: the stored coefficients (f32) reproduce the stored error.
        for i in (0..q.entries().len()).step_by(7) {
            let e = &q.entries()[i];
            let rgb = sys.rgb(&e.coefficients);
            let target = q.entry_rgb(i);
            let err = (0..3).map(|k| (rgb[k] - target[k]).powi(2)).sum::<f64>().sqrt();
            assert!((err - e.error).abs() < 1e-3, "entry {i}: {err} vs stored {}", e.error);
            if e.coefficients.concentration == 0.0 {
                assert!(err < REMAINING_ERROR || e.reflectance_only_error > FLUORESCENCE_TRIGGER);
            }
            // fluorescence never makes an entry worse than reflectance alone
            assert!(e.error <= e.reflectance_only_error + 1e-4, "entry {i}");
        }
        // Grey entries are plain reflectances.
        let mid = q.entries()[(2 * 5 + 2) * 5 + 2];
        assert_eq!(mid.coefficients.concentration, 0.0);
        assert!(mid.error < 1e-4);
    }

    #[test]
    fn regenerated_small_cube_agrees_with_shipped_entries() {
        // Res 5 grid points k/4 are entries 8k of the res-33 grid: regenerate (CI) and
        // compare a sample of entries with the shipped cube.
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/cubes/acescg_d65_tinf_r33.cube");
        let shipped = Cube::load(&path).unwrap();
        let settings = CubeSettings {
            space: RgbSpace::AcesCg,
            illuminant: "D65".into(),
            resolution: 5,
            threshold: f64::INFINITY,
            rounds: 4,
            threads: 2,
        };
        let (small, _) = generate_cube(&settings, &mut |_| {}).unwrap();
        let small = small.quantised().unwrap();
        let sys = small.colour_system().unwrap();
        for i in (0..125).step_by(3) {
            let (a, b, c) = (i / 25, (i / 5) % 5, i % 5);
            let j = ((8 * a) * 33 + 8 * b) * 33 + 8 * c;
            assert_eq!(small.entry_rgb(i), shipped.entry_rgb(j));
            let (es, eb) = (&small.entries()[i], &shipped.entries()[j]);
            // both plain reflectances where the shipped one is
            if eb.coefficients.concentration == 0.0 && eb.error < 1e-3 {
                assert!(es.error < 1e-3 && es.coefficients.concentration == 0.0, "entry {:?}", small.entry_rgb(i));
            }
            // reflectance-only stage reaches the same error level
            assert!(
                (es.reflectance_only_error - eb.reflectance_only_error).abs() < 5e-3 + 0.1 * eb.reflectance_only_error
            );
            let rgb = sys.rgb(&es.coefficients);
            let err = (0..3).map(|k| (rgb[k] - small.entry_rgb(i)[k]).powi(2)).sum::<f64>().sqrt();
            assert!((err - es.error).abs() < 1e-4);
        }
    }
}
