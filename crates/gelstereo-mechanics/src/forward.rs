//! The forward normal contact problem: a rigid frictionless indenter pressed into the layer.
//!
//! With `pen` the indenter's rigid overlap at each node (how far the undeformed surface would
//! have to move into the gel to clear it), the pressure `p >= 0` makes the surface displacement
//! `w = C_nn p` meet `w >= pen` everywhere, with equality where `p > 0`: the minimum of
//! `½ pᵀ C p − penᵀ p` over `p >= 0`. Solved by the conjugate gradients of Polonsky & Keer
//! (*Wear* 231, 1999) restricted to the loaded nodes, with nodes that penetrate re-admitted.

use crate::influence::{Influence, Vec3, Workspace};

/// Iterations of the conjugate-gradient contact solver, at most.
const MAX_ITERATIONS: usize = 500;

/// The solution of a forward contact problem.
#[derive(Debug, Clone)]
pub struct Indentation {
    /// Pressure per node, kPa (row-major over the lattice).
    pub pressure_kpa: Vec<f64>,
    /// Surface displacement per node `[ux, uy, w]`, mm (including the lateral pull of the
    /// pressure on a compressible layer).
    pub displacement_mm: Vec<Vec3>,
    /// Iterations used.
    pub iterations: usize,
}

impl Indentation {
    /// Total normal force, N.
    pub fn force_n(&self, spacing_mm: f64) -> f64 {
        self.pressure_kpa.iter().sum::<f64>() * spacing_mm * spacing_mm * 1e-3
    }
}

/// Presses the rigid overlap `pen_mm` (row-major over the operator's lattice) into the layer:
/// the pressure and the displacement, to a relative tolerance `tolerance` on the gap.
pub fn indent(op: &Influence, pen_mm: &[f64], tolerance: f64) -> Indentation {
    let n = op.rows() * op.cols();
    assert_eq!(pen_mm.len(), n, "the overlap must cover the lattice");
    let mut work = Workspace::default();
    let normal = |p: &[f64], out: &mut Vec<Vec3>, work: &mut Workspace| {
        let t: Vec<Vec3> = p.iter().map(|&v| [0.0, 0.0, v]).collect();
        op.apply(&t, out, work);
    };
    // The tolerance is relative to the deepest overlap: the free surface's (negative) overlap far
    // from the indenter says nothing of the contact's scale.
    let scale = pen_mm.iter().fold(0.0f64, |m, v| m.max(*v)).max(1e-12);
    let mut p: Vec<f64> = pen_mm
        .iter()
        .map(|&v| {
            if v > 0.0 {
                v.max(0.0) / op.norm() * 0.1
            } else {
                0.0
            }
        })
        .collect();
    let mut u = vec![[0.0; 3]; n];
    let mut r = vec![[0.0; 3]; n];
    let mut dir = vec![0.0; n];
    let (mut g_old, mut conjugate) = (1.0, false);
    let mut iterations = 0;
    for it in 0..MAX_ITERATIONS {
        iterations = it + 1;
        normal(&p, &mut u, &mut work);
        let gap: Vec<f64> = u.iter().zip(pen_mm).map(|(u, pen)| u[2] - pen).collect();
        let g: f64 = (0..n).filter(|&k| p[k] > 0.0).map(|k| gap[k] * gap[k]).sum();
        for k in 0..n {
            dir[k] = if p[k] > 0.0 {
                gap[k] + if conjugate { g / g_old * dir[k] } else { 0.0 }
            } else {
                0.0
            };
        }
        g_old = g.max(f64::MIN_POSITIVE);
        normal(&dir, &mut r, &mut work);
        let num: f64 = (0..n).filter(|&k| p[k] > 0.0).map(|k| gap[k] * dir[k]).sum();
        let den: f64 = (0..n).filter(|&k| p[k] > 0.0).map(|k| r[k][2] * dir[k]).sum();
        let step = if den > 0.0 { num / den } else { 0.0 };
        let mut admitted = false;
        for k in 0..n {
            if p[k] > 0.0 {
                p[k] = (p[k] - step * dir[k]).max(0.0);
            } else if gap[k] < 0.0 {
                // A free node that penetrates: load it (and restart the conjugate directions).
                p[k] = -step.max(1.0 / op.norm()) * gap[k];
                admitted = true;
            }
        }
        conjugate = !admitted;
        let worst = gap
            .iter()
            .zip(&p)
            .map(|(g, p)| if *p > 0.0 { g.abs() } else { (-g).max(0.0) })
            .fold(0.0, f64::max);
        if it > 0 && worst < tolerance * scale {
            break;
        }
    }
    let t: Vec<Vec3> = p.iter().map(|&v| [0.0, 0.0, v]).collect();
    op.apply(&t, &mut u, &mut work);
    Indentation {
        pressure_kpa: p,
        displacement_mm: u,
        iterations,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layer::Layer;

    /// A sphere on a layer much thicker than the contact: Hertz (`F = 4/3 E* R^½ d^{3/2}`,
    /// `a = (R d)^½`) with the stiffening of a bonded layer of finite thickness to second order in
    /// `χ = a / h` (Dimitriadis et al., *Biophys. J.* 82, 2002, their bonded compressible case);
    /// the contact radius (7 pitches) with its edge placed below the pitch by `ContactLoad`.
    #[test]
    fn a_sphere_on_a_thick_layer_follows_hertz() {
        let gel = Layer {
            thickness_mm: 8.0,
            modulus_kpa: 200.0,
            poisson: 0.4,
        };
        let (n, a) = (41, 0.1);
        let op = Influence::new(&gel, n, n, a).unwrap();
        let (radius, depth) = (10.0, 0.05);
        let pen: Vec<f64> = (0..n * n)
            .map(|k| {
                let (x, y) = (((k % n) as f64 - 20.0) * a, ((k / n) as f64 - 20.0) * a);
                depth - (x * x + y * y) / (2.0 * radius)
            })
            .collect();
        let sol = indent(&op, &pen, 1e-6);
        let nu = gel.poisson;
        let e_star = gel.plane_strain_modulus_kpa();
        let chi = (radius * depth).sqrt() / gel.thickness_mm;
        let alpha = -(1.2876 - 1.4678 * nu + 1.3442 * nu * nu) / (1.0 - nu);
        let pi = std::f64::consts::PI;
        let layer = 1.0 - 2.0 * alpha / pi * chi + 4.0 * alpha * alpha / (pi * pi) * chi * chi;
        let hertz_force = 4.0 / 3.0 * e_star * radius.sqrt() * depth.powf(1.5) * 1e-3;
        let force = sol.force_n(a);
        let area = crate::inverse::ContactLoad::new(
            &crate::inverse::Tractions {
                traction_kpa: sol.pressure_kpa.iter().map(|&p| [0.0, 0.0, p]).collect(),
                iterations: 0,
                noise_pressure_kpa: 0.0,
                selected_kpa: sol.pressure_kpa.clone(),
            },
            n,
            n,
            a,
            None,
        )
        .area_mm2;
        let hertz_area = pi * radius * depth;
        assert!(
            (force / (hertz_force * layer) - 1.0).abs() < 0.04,
            "force {force} vs {hertz_force} x {layer}"
        );
        assert!(
            (area / hertz_area - 1.0).abs() < 0.05,
            "area {area} vs {hertz_area}"
        );
    }
}
