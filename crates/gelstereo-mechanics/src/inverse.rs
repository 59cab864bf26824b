//! The inverse problem: the surface tractions that explain measured 3-D marker displacements.
//!
//! Unknowns: the traction `[τx, τy, p]` on each lattice cell. They minimise
//! `½ |C t − u|² + λ Σ p` subject to `|τ| <= m p` at every cell: the pressure is compressive and
//! a cell carries shear only where it is pressed (no adhesion). `m` bounds the friction
//! coefficient from above, so the constraint never decides between stick and slip; it only keeps
//! shear out of the free surface. `λ` is set from the measurement noise (see
//! [`InverseConfig::sparsity`]). Markers without a measurement take the mean of their measured
//! neighbours' displacements first. The solver is ADMM (Boyd et al. 2011) split between the
//! least-squares part, solved exactly per frequency by FFT (`(C² + ρ)⁻¹`, precomputed), and
//! the cone, a projection per cell; warm-started from the previous frame it needs few
//! iterations.

use crate::error::{Error, Result, invalid};
use rustfft::num_complex::Complex64;

use crate::influence::{Influence, Matrix3, Vec3, Workspace};

/// Settings of the inverse solver.
#[derive(Debug, Clone, PartialEq)]
pub struct InverseConfig {
    /// Largest ratio of shear to pressure a cell may carry (the friction cone's closure), above
    /// any real gel's friction coefficient.
    pub friction_bound: f64,
    /// Iterations at most (of each of the two fits).
    pub max_iterations: usize,
    /// ADMM's penalty as a fraction of the operator's largest squared eigenvalue.
    pub penalty: f64,
    /// Stop when an iteration changes the tractions by less than this fraction of their size.
    pub tolerance: f64,
    /// Noise of the data reaches the pressure's gradient as `σ` times the operator's row norm;
    /// a cell is loaded only where the data pull harder than this many such standard
    /// deviations (an L1 penalty on the pressure), so that the nonnegativity does not rectify
    /// the noise into a spurious load spread over the free surface.
    pub sparsity: f64,
}

impl Default for InverseConfig {
    fn default() -> Self {
        Self {
            friction_bound: 2.0,
            max_iterations: 300,
            penalty: 0.03,
            tolerance: 5e-3,
            sparsity: 4.0,
        }
    }
}

impl InverseConfig {
    /// Checks the settings' ranges.
    pub fn validate(&self) -> Result<()> {
        if !(self.friction_bound.is_finite() && self.friction_bound > 0.0) {
            return Err(invalid("friction_bound", "a positive ratio", self.friction_bound));
        }
        if !(1..=100_000).contains(&self.max_iterations) {
            return Err(invalid("max_iterations", "1 to 100000", self.max_iterations));
        }
        if !(self.penalty.is_finite() && self.penalty > 0.0) {
            return Err(invalid("penalty", "a positive fraction", self.penalty));
        }
        if !(self.sparsity.is_finite() && self.sparsity >= 0.0) {
            return Err(invalid(
                "sparsity",
                "a non-negative number of standard deviations",
                self.sparsity,
            ));
        }
        if !(self.tolerance.is_finite() && self.tolerance > 0.0) {
            return Err(invalid("tolerance", "a positive fraction", self.tolerance));
        }
        Ok(())
    }
}

/// A cell is in contact where its penalised pressure exceeds this many times the pressure of one
/// standard deviation of noise reaching it (`σ / |C_p|`): next to a contact the fit can move a
/// little load onto the cells around it at little cost, and this keeps them out.
const CONTACT_NOISE: f64 = 1.0;
/// A cell is in contact only above this fraction of the largest pressure: where the gel departs
/// from the ideal layer (or the data from its noise model) the fit spreads a faint load over the
/// free surface to explain it, while a real contact's edge region below a tenth of its peak
/// pressure is thin (Hertz: the outer half percent of the radius).
const CONTACT_FLOOR: f64 = 0.1;

/// ADMM's over-relaxation (Boyd et al. 2011, § 3.4.3): the cone's projection and the dual
/// update see `α x + (1 − α) z` in place of `x`, which takes fewer iterations to the same
/// solution.
const RELAXATION: f64 = 1.8;

/// Solves the inverse problem frame after frame on one lattice.
#[derive(Debug, Clone)]
pub struct InverseSolver {
    op: Influence,
    config: InverseConfig,
    work: Workspace,
    /// ADMM's penalty, (mm / kPa)².
    rho: f64,
    /// Per frequency: `ρ (C² + ρ)⁻¹` and `(C² + ρ)⁻¹ C`.
    solve: Vec<Hermitian3>,
    project_data: Vec<Matrix3>,
    /// The last frame's tractions and scaled dual (the next frame's start).
    previous: Vec<Vec3>,
    previous_dual: Vec<Vec3>,
}

/// The tractions of one frame.
#[derive(Debug, Clone)]
pub struct Tractions {
    /// `[τx, τy, p]` per lattice cell, kPa, row-major.
    pub traction_kpa: Vec<Vec3>,
    /// Iterations used.
    pub iterations: usize,
    /// The pressure the data's noise alone can put on a cell, kPa: cells above it are in contact.
    pub noise_pressure_kpa: f64,
    /// The pressure per cell of the first, penalised fit, kPa: it selects the cells in contact
    /// (the refitted pressure places the edge between them and the free ones).
    pub selected_kpa: Vec<f64>,
}

impl InverseSolver {
    /// A solver on the lattice and layer of `op`.
    pub fn new(op: Influence, config: InverseConfig) -> Result<Self> {
        config.validate()?;
        let n = op.rows() * op.cols();
        let rho = config.penalty * op.norm() * op.norm();
        let eye = Matrix3(std::array::from_fn(|r| {
            std::array::from_fn(|c| Complex64::new(if r == c { rho } else { 0.0 }, 0.0))
        }));
        let (solve, project_data): (Vec<Hermitian3>, Vec<Matrix3>) = op
            .matrices()
            .map(|m| {
                let mut sq = m.mul_matrix(&m);
                for (r, row) in sq.0.iter_mut().enumerate() {
                    row[r] += eye.0[r][r];
                }
                let inv = sq.inverse();
                (Hermitian3::scaled(&inv, rho), inv.mul_matrix(&m))
            })
            .unzip();
        Ok(Self {
            op,
            config,
            work: Workspace::default(),
            rho,
            solve,
            project_data,
            previous: vec![[0.0; 3]; n],
            previous_dual: vec![[0.0; 3]; n],
        })
    }

    /// The influence operator.
    pub fn influence(&self) -> &Influence {
        &self.op
    }

    /// Forgets the last frame (the next solve starts from zero traction).
    pub fn reset(&mut self) {
        self.previous.iter_mut().for_each(|t| *t = [0.0; 3]);
        self.previous_dual.iter_mut().for_each(|t| *t = [0.0; 3]);
    }

    /// The tractions that explain `displacement_mm` (`[ux, uy, w]` per marker in the gel frame,
    /// row-major over the lattice, `None` where not measured), for a displacement noise of
    /// `noise_mm` (standard deviations `[tangential, normal]`).
    pub fn solve(&mut self, displacement_mm: &[Option<Vec3>], noise_mm: [f64; 2]) -> Result<Tractions> {
        let n = self.op.rows() * self.op.cols();
        if displacement_mm.len() != n {
            return Err(Error::Mismatch {
                what: "displacements",
                expected: format!("{n} markers ({} x {} lattice)", self.op.rows(), self.op.cols()),
                found: format!("{}", displacement_mm.len()),
            });
        }
        let u = fill_missing(displacement_mm, self.op.rows(), self.op.cols());
        let [tangential, normal] = noise_mm.map(|v| if v.is_finite() { v.max(0.0) } else { 0.0 });
        let (row_n, row_t) = self.op.pressure_row_norms();
        let lambda = self.config.sparsity * (normal * row_n).hypot(tangential * row_t);
        // The data's part of every x-update, `(C² + ρ)⁻¹ C u`, in the frequency domain.
        self.op.transform(&u, &mut self.work);
        let data: [Vec<Complex64>; 3] = {
            let [px, py, pn] = &self.work.planes;
            let v: Vec<[Complex64; 3]> = self
                .project_data
                .iter()
                .enumerate()
                .map(|(k, b)| b.mul([px[k], py[k], pn[k]]))
                .collect();
            std::array::from_fn(|c| v.iter().map(|x| x[c]).collect())
        };
        // The L1 penalty finds the cells in contact, then the tractions are refitted on those
        // cells without it: the penalty would shrink the load it keeps.
        let mut z = self.previous.clone();
        let mut w = self.previous_dual.clone();
        let mut iterations = self.admm(&mut z, &mut w, &data, lambda, None);
        let peak = z.iter().fold(0.0f64, |m, t| m.max(t[2]));
        let noise_pressure =
            (CONTACT_NOISE * normal.hypot(tangential * row_t / row_n) / row_n).max(CONTACT_FLOOR * peak);
        let support: Vec<bool> = z.iter().map(|t| t[2] > noise_pressure).collect();
        let selected_kpa: Vec<f64> = z.iter().map(|t| t[2]).collect();
        self.previous.copy_from_slice(&z);
        self.previous_dual.copy_from_slice(&w);
        iterations += self.admm(&mut z, &mut w, &data, 0.0, Some(&support));
        Ok(Tractions {
            traction_kpa: z,
            iterations,
            noise_pressure_kpa: noise_pressure,
            selected_kpa,
        })
    }

    /// Scaled ADMM on `½ |C x − u|² + λ Σ p` with `x = z`, `z` in the cone (and, with `support`,
    /// zero off it), from `z` and the scaled dual `w`; the iterations used. `data` holds
    /// `(C² + ρ)⁻¹ C û`.
    fn admm(
        &mut self,
        z: &mut [Vec3],
        w: &mut [Vec3],
        data: &[Vec<Complex64>; 3],
        lambda: f64,
        support: Option<&[bool]>,
    ) -> usize {
        let n = z.len();
        let m = self.config.friction_bound;
        let rho = self.rho;
        let mut x = vec![[0.0; 3]; n];
        let mut v = vec![[0.0; 3]; n];
        let mut iterations = 0;
        for it in 0..self.config.max_iterations {
            iterations = it + 1;
            // x = (C² + ρ)⁻¹ (C u + ρ (z − w)).
            for k in 0..n {
                v[k] = std::array::from_fn(|c| z[k][c] - w[k][c]);
            }
            self.op.transform(&v, &mut self.work);
            {
                let [px, py, pn] = &mut self.work.planes;
                for (k, a) in self.solve.iter().enumerate() {
                    let s = a.mul([px[k], py[k], pn[k]]);
                    px[k] = data[0][k] + s[0];
                    py[k] = data[1][k] + s[1];
                    pn[k] = data[2][k] + s[2];
                }
            }
            self.op.untransform(&mut self.work, &mut x);
            let (mut primal, mut dual, mut size, mut dual_size) = (0.0, 0.0, 0.0, 0.0);
            for k in 0..n {
                let relaxed: Vec3 =
                    std::array::from_fn(|c| RELAXATION * x[k][c] + (1.0 - RELAXATION) * z[k][c]);
                let mut shifted: Vec3 = std::array::from_fn(|c| relaxed[c] + w[k][c]);
                shifted[2] -= lambda / rho;
                let next = if support.is_none_or(|s| s[k]) {
                    project(shifted, m)
                } else {
                    [0.0; 3]
                };
                for c in 0..3 {
                    dual += (next[c] - z[k][c]).powi(2);
                    z[k][c] = next[c];
                    let r = x[k][c] - next[c];
                    primal += r * r;
                    w[k][c] += relaxed[c] - next[c];
                    size += x[k][c].powi(2).max(next[c].powi(2));
                    dual_size += w[k][c].powi(2);
                }
            }
            let tol = self.config.tolerance.powi(2);
            if it > 0 && primal <= tol * size.max(f64::MIN_POSITIVE) && dual <= tol * dual_size.max(size) {
                break;
            }
        }
        iterations
    }
}

/// The displacements with every marker that lacks one given the mean of its measured (or
/// already filled) 8-neighbours', sweeping until all are filled; zero where nothing is measured.
fn fill_missing(displacement_mm: &[Option<Vec3>], rows: usize, cols: usize) -> Vec<Vec3> {
    let mut known: Vec<Option<Vec3>> = displacement_mm
        .iter()
        .map(|d| d.filter(|d| d.iter().all(|v| v.is_finite())))
        .collect();
    while known.iter().any(Option::is_none) {
        let before = known.clone();
        for r in 0..rows {
            for c in 0..cols {
                if before[r * cols + c].is_some() {
                    continue;
                }
                let (mut sum, mut count) = ([0.0; 3], 0.0);
                for rr in r.saturating_sub(1)..=(r + 1).min(rows - 1) {
                    for cc in c.saturating_sub(1)..=(c + 1).min(cols - 1) {
                        if let Some(d) = before[rr * cols + cc] {
                            (0..3).for_each(|i| sum[i] += d[i]);
                            count += 1.0;
                        }
                    }
                }
                if count > 0.0 {
                    known[r * cols + c] = Some(sum.map(|s| s / count));
                }
            }
        }
        if known == before {
            break;
        }
    }
    known.into_iter().map(|d| d.unwrap_or([0.0; 3])).collect()
}

/// What a frame's tractions add up to.
#[derive(Debug, Clone, PartialEq)]
pub struct ContactLoad {
    /// Whether each cell is in contact (its pressure above the noise's), row-major.
    pub in_contact: Vec<bool>,
    /// Contact area, mm², with the edge placed below the pitch (see [`ContactLoad::new`]).
    pub area_mm2: f64,
    /// Total normal force, N (pressure over the cells in contact).
    pub force_n: f64,
    /// Total tangential force on the gel `[x, y]`, N.
    pub shear_n: [f64; 2],
    /// Pressure centroid `[x, y]`, mm, in lattice coordinates: `x = col · pitch`, `y = row ·
    /// pitch`; `None` without contact.
    pub centroid_mm: Option<[f64; 2]>,
    /// Torque of the tangential tractions about the normal through the pressure centroid, N mm
    /// (positive from x towards y).
    pub torque_nmm: f64,
}

impl ContactLoad {
    /// Sums the tractions of the cells in contact of a `rows x cols` lattice of pitch
    /// `spacing_mm`: those whose pressure exceeds the noise's and, with `allowed`, that it
    /// allows. The area counts each cell in contact, then moves each side that borders a
    /// cell out of contact to where the pressure vanishes: `p²` falls linearly to the edge of a
    /// smooth contact (Hertz: `p² ∝ a² − r²`), extrapolated from the cell and its neighbour
    /// inwards, within one pitch; half a pitch where the pressure rises towards the edge (a
    /// flat punch) and the edge cannot be placed.
    pub fn new(t: &Tractions, rows: usize, cols: usize, spacing_mm: f64, allowed: Option<&[bool]>) -> Self {
        let p = |k: usize| t.selected_kpa[k];
        let in_contact: Vec<bool> = (0..rows * cols)
            .map(|k| p(k) > t.noise_pressure_kpa && allowed.is_none_or(|a| a[k]))
            .collect();
        let cell = spacing_mm * spacing_mm;
        let (mut force, mut shear, mut moment) = (0.0, [0.0; 2], [0.0; 2]);
        let mut area = 0.0;
        for r in 0..rows {
            for c in 0..cols {
                let k = r * cols + c;
                if !in_contact[k] {
                    continue;
                }
                let [tx, ty, load] = t.traction_kpa[k];
                force += load;
                shear[0] += tx;
                shear[1] += ty;
                moment[0] += load * c as f64;
                moment[1] += load * r as f64;
                let pk = load;
                area += 1.0;
                for (dr, dc) in [(0isize, 1isize), (0, -1), (1, 0), (-1, 0)] {
                    let at = |s: isize| {
                        let (rr, cc) = (r as isize + s * dr, c as isize + s * dc);
                        (rr >= 0 && cc >= 0 && (rr as usize) < rows && (cc as usize) < cols)
                            .then(|| rr as usize * cols + cc as usize)
                    };
                    if at(1).is_some_and(|o| in_contact[o]) {
                        continue;
                    }
                    let edge = match at(-1).filter(|&j| in_contact[j]) {
                        Some(j) if t.traction_kpa[j][2] > pk => {
                            let pj = t.traction_kpa[j][2];
                            (pk * pk / (pj * pj - pk * pk)).min(1.0)
                        }
                        _ => 0.5,
                    };
                    area += edge - 0.5;
                }
            }
        }
        let centroid =
            (force > 0.0).then(|| [moment[0] / force * spacing_mm, moment[1] / force * spacing_mm]);
        let mut torque = 0.0;
        if let Some([cx, cy]) = centroid {
            for (k, _) in in_contact.iter().enumerate().filter(|(_, c)| **c) {
                let (x, y) = (
                    (k % cols) as f64 * spacing_mm - cx,
                    (k / cols) as f64 * spacing_mm - cy,
                );
                let [tx, ty, _] = t.traction_kpa[k];
                torque += x * ty - y * tx;
            }
        }
        // kPa · mm² = 1e-3 N.
        Self {
            in_contact,
            area_mm2: area * cell,
            force_n: force * cell * 1e-3,
            shear_n: shear.map(|s| s * cell * 1e-3),
            centroid_mm: centroid,
            torque_nmm: torque * cell * 1e-3,
        }
    }
}

/// A Hermitian 3 x 3 matrix: its real diagonal and the upper triangle `[01, 02, 12]`.
#[derive(Debug, Clone, Copy)]
struct Hermitian3 {
    diagonal: [f64; 3],
    upper: [Complex64; 3],
}

impl Hermitian3 {
    /// `scale · m` of a matrix `m` that is Hermitian up to rounding (its upper triangle).
    fn scaled(m: &Matrix3, scale: f64) -> Self {
        let m = &m.0;
        Self {
            diagonal: [m[0][0].re, m[1][1].re, m[2][2].re].map(|v| v * scale),
            upper: [m[0][1], m[0][2], m[1][2]].map(|v| v * scale),
        }
    }

    fn mul(&self, v: [Complex64; 3]) -> [Complex64; 3] {
        let ([d0, d1, d2], [a, b, c]) = (self.diagonal, self.upper);
        [
            v[0] * d0 + a * v[1] + b * v[2],
            a.conj() * v[0] + v[1] * d1 + c * v[2],
            b.conj() * v[0] + c.conj() * v[1] + v[2] * d2,
        ]
    }
}

/// Euclidean projection of `[τx, τy, p]` onto the cone `|τ| <= m p`.
fn project(t: Vec3, m: f64) -> Vec3 {
    let (s2, p) = (t[0] * t[0] + t[1] * t[1], t[2]);
    // Inside the cone (compared squared: a cell inside needs no square root).
    if p >= 0.0 && s2 <= m * m * p * p {
        return t;
    }
    let s = s2.sqrt();
    // Onto the cone's surface ray (m, 1) in the (|τ|, p) plane, or the apex.
    let along = (m * s + p) / (1.0 + m * m);
    if along <= 0.0 {
        return [0.0; 3];
    }
    let scale = m * along / s;
    [t[0] * scale, t[1] * scale, along]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forward::indent;
    use crate::layer::Layer;

    const GEL: Layer = Layer::REFERENCE;

    #[test]
    fn the_projection_lands_on_the_cone() {
        assert_eq!(project([0.3, 0.4, 1.0], 1.0), [0.3, 0.4, 1.0]);
        assert_eq!(project([0.3, 0.4, -1.0], 1.0), [0.0; 3]);
        let p = project([3.0, 4.0, 1.0], 1.0);
        assert!(
            (p[0].hypot(p[1]) - p[2]).abs() < 1e-12 && (p[2] - 3.0).abs() < 1e-12,
            "{p:?}"
        );
    }

    /// A deterministic standard normal generator (xorshift and Box–Muller), for reproducible noise.
    fn normal_noise(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        let mut uniform = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        move || (-2.0 * uniform().ln()).sqrt() * (2.0 * std::f64::consts::PI * uniform()).cos()
    }

    /// Spheres pressed into the reference gel (forward contact on the lattice), seen with 0.01 mm
    /// of noise on every displacement component: force comes back within 5 % and area within 20 %, the
    /// centroid within a quarter pitch, and nothing shears a frictionless press.
    #[test]
    fn pressed_spheres_are_recovered_from_noisy_displacements() {
        let (n, a) = (23, 0.8);
        let op = Influence::new(&GEL, n, n, a).unwrap();
        let mut noise = normal_noise(0x2545_F491_4F6C_DD1D);
        for (radius, depth, cx, cy) in [
            (6.0, 0.5, 0.24, -0.16),
            (10.0, 0.8, -1.1, 0.5),
            (4.0, 0.4, 0.0, 0.0),
        ] {
            let pen: Vec<f64> = (0..n * n)
                .map(|k| {
                    let (x, y) = (((k % n) as f64 - 11.0) * a - cx, ((k / n) as f64 - 11.0) * a - cy);
                    depth - (x * x + y * y) / (2.0 * radius)
                })
                .collect();
            let truth = indent(&op, &pen, 1e-7);
            let true_area = ContactLoad::new(
                &Tractions {
                    traction_kpa: truth.pressure_kpa.iter().map(|&p| [0.0, 0.0, p]).collect(),
                    iterations: 0,
                    noise_pressure_kpa: 0.0,
                    selected_kpa: truth.pressure_kpa.clone(),
                },
                n,
                n,
                a,
                None,
            )
            .area_mm2;
            let sigma = 0.01;
            let u: Vec<Option<Vec3>> = truth
                .displacement_mm
                .iter()
                .map(|d| Some(d.map(|v| v + sigma * noise())))
                .collect();
            let mut solver = InverseSolver::new(op.clone(), InverseConfig::default()).unwrap();
            let load = ContactLoad::new(&solver.solve(&u, [sigma; 2]).unwrap(), n, n, a, None);
            let want = truth.force_n(a);
            assert!(
                (load.force_n / want - 1.0).abs() < 0.05,
                "force {} vs {want}",
                load.force_n
            );
            assert!(
                (load.area_mm2 / true_area - 1.0).abs() < 0.2,
                "area {} vs {true_area}",
                load.area_mm2
            );
            let [x, y] = load.centroid_mm.unwrap();
            assert!(
                (x - 11.0 * a - cx).hypot(y - 11.0 * a - cy) < 0.25 * a,
                "centroid {x} {y}"
            );
            assert!(
                load.shear_n[0].hypot(load.shear_n[1]) < 0.05 * want,
                "{:?}",
                load.shear_n
            );
        }
    }
}
