//! The inverse problem: the surface tractions that explain measured 3-D marker displacements.
//!
//! Unknowns: the traction `[τx, τy, p]` on each lattice cell. They minimise
//! `½ Σ_observed |C t − u|² + ½ α |t|²` subject to `|τ| <= m p` at every cell: the pressure is
//! compressive and a cell carries shear only where it is pressed (no adhesion). `m` bounds the
//! friction coefficient from above, so the constraint never decides between stick and slip; it
//! only keeps shear out of the free surface. `α` weighs a traction prior of the layer's own scale
//! against the measurement noise: `α = (σ_u / σ_t)²` with `σ_t` the modulus. The solver is
//! FISTA (Beck & Teboulle 2009) with adaptive restart, projecting onto the cone at each step;
//! warm-started from the previous frame's tractions it needs few iterations.

use crate::error::{Error, Result};
use crate::influence::{Influence, Vec3, Workspace};

/// Settings of the inverse solver.
#[derive(Debug, Clone, PartialEq)]
pub struct InverseConfig {
    /// Largest ratio of shear to pressure a cell may carry (the friction cone's closure), above
    /// any real gel's friction coefficient.
    pub friction_bound: f64,
    /// Iterations at most.
    pub max_iterations: usize,
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
            tolerance: 1e-4,
            sparsity: 4.0,
        }
    }
}

impl InverseConfig {
    /// Checks the settings' ranges.
    pub fn validate(&self) -> Result<()> {
        if !(self.friction_bound.is_finite() && self.friction_bound > 0.0) {
            return Err(Error::Invalid {
                field: "friction_bound",
                expected: "a positive ratio".into(),
                found: format!("{}", self.friction_bound),
            });
        }
        if !(1..=100_000).contains(&self.max_iterations) {
            return Err(Error::Invalid {
                field: "max_iterations",
                expected: "1 to 100000".into(),
                found: format!("{}", self.max_iterations),
            });
        }
        if !(self.sparsity.is_finite() && self.sparsity >= 0.0) {
            return Err(Error::Invalid {
                field: "sparsity",
                expected: "a non-negative number of standard deviations".into(),
                found: format!("{}", self.sparsity),
            });
        }
        if !(self.tolerance.is_finite() && self.tolerance > 0.0) {
            return Err(Error::Invalid {
                field: "tolerance",
                expected: "a positive fraction".into(),
                found: format!("{}", self.tolerance),
            });
        }
        Ok(())
    }
}

/// A cell is in contact where its pressure exceeds this many times the pressure of one standard
/// deviation of noise reaching it (`σ / |C_p|`): the L1 penalty keeps noise below a few of them,
/// and the iterate's small remainders below one.
const CONTACT_NOISE: f64 = 0.5;
/// With noise-free data, a cell is in contact above this fraction of the largest pressure (the
/// iterate's remainders are far below it).
const CONTACT_FLOOR: f64 = 0.01;

/// Solves the inverse problem frame after frame on one lattice.
#[derive(Debug, Clone)]
pub struct InverseSolver {
    op: Influence,
    config: InverseConfig,
    modulus_kpa: f64,
    work: Workspace,
    /// The last frame's tractions (the next frame's start).
    previous: Vec<Vec3>,
}

/// The tractions of one frame.
#[derive(Debug, Clone)]
pub struct Tractions {
    /// `[τx, τy, p]` per lattice cell, kPa, row-major.
    pub traction_kpa: Vec<Vec3>,
    /// Iterations used.
    pub iterations: usize,
    /// RMS misfit of the displacement over the observed markers, mm.
    pub misfit_mm: f64,
    /// The pressure the data's noise alone can put on a cell, kPa: cells above it are in contact.
    pub noise_pressure_kpa: f64,
    /// The pressure per cell of the first, penalised fit, kPa: it selects the cells in contact
    /// and places the contact's edge; the penalty shrinks it by about the noise's pressure
    /// everywhere, which keeps noise at the edge from pushing it outwards.
    pub selected_kpa: Vec<f64>,
}

impl InverseSolver {
    /// A solver for the layer `op` was built for (`modulus_kpa`: its Young's modulus).
    pub fn new(op: Influence, modulus_kpa: f64, config: InverseConfig) -> Result<Self> {
        config.validate()?;
        let n = op.rows() * op.cols();
        Ok(Self {
            op,
            config,
            modulus_kpa,
            work: Workspace::default(),
            previous: vec![[0.0; 3]; n],
        })
    }

    /// The influence operator.
    pub fn influence(&self) -> &Influence {
        &self.op
    }

    /// Forgets the last frame (the next solve starts from zero traction).
    pub fn reset(&mut self) {
        self.previous.iter_mut().for_each(|t| *t = [0.0; 3]);
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
        let observed: Vec<bool> = displacement_mm
            .iter()
            .map(|d| d.is_some_and(|d| d.iter().all(|v| v.is_finite())))
            .collect();
        let u: Vec<Vec3> = displacement_mm
            .iter()
            .zip(&observed)
            .map(|(d, &ok)| if ok { d.unwrap_or([0.0; 3]) } else { [0.0; 3] })
            .collect();
        let [tangential, normal] = noise_mm.map(|v| if v.is_finite() { v.max(0.0) } else { 0.0 });
        let alpha = (normal.max(tangential) / self.modulus_kpa).powi(2);
        let (row_n, row_t) = self.op.pressure_row_norms();
        let lambda = self.config.sparsity * (normal * row_n).hypot(tangential * row_t);
        let m = self.config.friction_bound;
        // The L1 penalty finds the cells in contact, then the tractions are refitted on those
        // cells without it: the penalty would shrink the load it keeps.
        let mut x = self.previous.clone();
        project_all(&mut x, m);
        let mut iterations = self.fista(&mut x, &u, &observed, lambda, alpha, None);
        let peak = x.iter().fold(0.0f64, |m, t| m.max(t[2]));
        let noise_pressure =
            (CONTACT_NOISE * normal.hypot(tangential * row_t / row_n) / row_n).max(CONTACT_FLOOR * peak);
        let support: Vec<bool> = x.iter().map(|t| t[2] > noise_pressure).collect();
        let selected_kpa: Vec<f64> = x.iter().map(|t| t[2]).collect();
        iterations += self.fista(&mut x, &u, &observed, 0.0, alpha, Some(&support));
        let mut cy = vec![[0.0; 3]; n];
        self.op.apply(&x, &mut cy, &mut self.work);
        let (mut sq, mut count) = (0.0, 0usize);
        for k in (0..n).filter(|&k| observed[k]) {
            for c in 0..3 {
                sq += (cy[k][c] - u[k][c]).powi(2);
            }
            count += 3;
        }
        self.previous.copy_from_slice(&x);
        Ok(Tractions {
            traction_kpa: x,
            iterations,
            misfit_mm: (sq / count.max(1) as f64).sqrt(),
            noise_pressure_kpa: noise_pressure,
            selected_kpa,
        })
    }

    /// FISTA with adaptive restart on `½ |M (C x − u)|² + ½ α |x|² + λ Σ p` over the cone (and,
    /// with `support`, zero traction off it), from `x`; the iterations used.
    fn fista(
        &mut self,
        x: &mut [Vec3],
        u: &[Vec3],
        observed: &[bool],
        lambda: f64,
        alpha: f64,
        support: Option<&[bool]>,
    ) -> usize {
        let n = x.len();
        let m = self.config.friction_bound;
        let step = 1.0 / (self.op.norm() * self.op.norm() + alpha);
        let mut y = x.to_vec();
        let mut x_old = x.to_vec();
        let mut residual = vec![[0.0; 3]; n];
        let mut grad = vec![[0.0; 3]; n];
        let mut theta = 1.0f64;
        let mut iterations = 0;
        for it in 0..self.config.max_iterations {
            iterations = it + 1;
            self.op.apply(&y, &mut residual, &mut self.work);
            for k in 0..n {
                for c in 0..3 {
                    residual[k][c] = if observed[k] {
                        residual[k][c] - u[k][c]
                    } else {
                        0.0
                    };
                }
            }
            self.op.apply(&residual, &mut grad, &mut self.work);
            x_old.copy_from_slice(x);
            for k in 0..n {
                for c in 0..3 {
                    x[k][c] = y[k][c] - step * (grad[k][c] + alpha * y[k][c]);
                }
                x[k][2] -= step * lambda;
                x[k] = if support.is_none_or(|s| s[k]) {
                    project(x[k], m)
                } else {
                    [0.0; 3]
                };
            }
            let (mut change, mut size, mut uphill) = (0.0, 0.0, 0.0);
            for k in 0..n {
                for c in 0..3 {
                    let d = x[k][c] - x_old[k][c];
                    change += d * d;
                    size += x[k][c] * x[k][c];
                    uphill += (y[k][c] - x[k][c]) * d;
                }
            }
            if it > 0 && change <= self.config.tolerance.powi(2) * size.max(f64::MIN_POSITIVE) {
                break;
            }
            // Adaptive restart (O'Donoghue & Candès 2015): drop the momentum when it points uphill.
            if uphill > 0.0 {
                theta = 1.0;
            }
            let theta_next = 0.5 * (1.0 + (1.0 + 4.0 * theta * theta).sqrt());
            let beta = (theta - 1.0) / theta_next;
            theta = theta_next;
            for k in 0..n {
                for c in 0..3 {
                    y[k][c] = x[k][c] + beta * (x[k][c] - x_old[k][c]);
                }
            }
        }
        iterations
    }
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
    /// `spacing_mm`. The area counts each cell in contact, then moves each side that borders a
    /// cell out of contact to where the pressure vanishes: `p²` falls linearly to the edge of a
    /// smooth contact (Hertz: `p² ∝ a² − r²`), extrapolated from the cell and its neighbour
    /// inwards, within one pitch; half a pitch where the pressure rises towards the edge (a
    /// flat punch) and the edge cannot be placed.
    pub fn new(t: &Tractions, rows: usize, cols: usize, spacing_mm: f64) -> Self {
        let p = |k: usize| t.selected_kpa[k];
        let in_contact: Vec<bool> = (0..rows * cols).map(|k| p(k) > t.noise_pressure_kpa).collect();
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
                let pk = p(k);
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
                        Some(j) if p(j) > pk => (pk * pk / (p(j) * p(j) - pk * pk)).min(1.0),
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

fn project_all(t: &mut [Vec3], m: f64) {
    t.iter_mut().for_each(|v| *v = project(*v, m));
}

/// Euclidean projection of `[τx, τy, p]` onto the cone `|τ| <= m p`.
fn project(t: Vec3, m: f64) -> Vec3 {
    let s = t[0].hypot(t[1]);
    let p = t[2];
    if s <= m * p {
        return t;
    }
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

    const GEL: Layer = Layer {
        thickness_mm: 2.5,
        modulus_kpa: 150.0,
        poisson: 0.45,
    };

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
    /// of noise on every displacement component: force comes back within 5 % and area within 15 %, the
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
                    misfit_mm: 0.0,
                    noise_pressure_kpa: 0.0,
                    selected_kpa: truth.pressure_kpa.clone(),
                },
                n,
                n,
                a,
            )
            .area_mm2;
            let sigma = 0.01;
            let u: Vec<Option<Vec3>> = truth
                .displacement_mm
                .iter()
                .map(|d| Some(d.map(|v| v + sigma * noise())))
                .collect();
            let mut solver =
                InverseSolver::new(op.clone(), GEL.modulus_kpa, InverseConfig::default()).unwrap();
            let load = ContactLoad::new(&solver.solve(&u, [sigma; 2]).unwrap(), n, n, a);
            let want = truth.force_n(a);
            assert!(
                (load.force_n / want - 1.0).abs() < 0.05,
                "force {} vs {want}",
                load.force_n
            );
            assert!(
                (load.area_mm2 / true_area - 1.0).abs() < 0.15,
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
