//! The gel: a linear elastic layer bonded to a rigid plate, and its surface compliance in Fourier
//! space.
//!
//! The layer occupies `-h < z < 0`; its base `z = -h` is bonded to the rigid plate (the sensor's
//! acrylic window), its top `z = 0` is the contact surface. A surface traction field of one
//! wave vector `k` makes a displacement field of the same wave vector, so each Fourier mode is
//! a plane-strain problem in the plane of `k` and `z` plus an anti-plane one across it. Solving
//! both with Papkovich–Neuber potentials (`u = [∇(φ + zψ) − 4(1−ν)ψ e_z] / 2μ`, φ and ψ harmonic)
//! under `u(−h) = 0` and the given traction at `z = 0` gives, with `x = |k| h`, `s = e^(−2x)` and
//! `κ = 3 − 4ν`:
//!
//! ```text
//! D            = κ (1 + s²) + (4x² + κ² + 1) s
//! normal       = (1−ν) [κ (1 − s²) − 4 x s] / (μ |k| D)      pressure -> displacement into the gel
//! longitudinal = (1−ν) [κ (1 − s²) + 4 x s] / (μ |k| D)      traction along k -> displacement along k
//! transverse   = tanh(x) / (μ |k|)                          traction across k -> displacement across k
//! coupling     = [4 x² s − (1−2ν) κ (1 − s)²] / (2 μ |k| D)
//! ```
//!
//! where a traction along `k̂` moves the surface into the gel by `i · coupling · (k̂ · τ̂)` and a
//! pressure moves it along `k̂` by `−i · coupling · p̂` (the operator is Hermitian, as reciprocity
//! demands). As `h → ∞` these are the half-space's Boussinesq and Cerruti compliances
//! (`(1−ν)/μ|k|`, `1/μ|k|`, `−(1−2ν)/2μ|k|`); as `k → 0`, the uniaxial strain of the layer
//! (`h (1−2ν) / 2μ(1−ν)`) and its simple shear (`h/μ`).
//!
//! Conventions: gel frame with `x, y` in the surface and `z` out of the gel towards the object;
//! the displacement into the gel (towards the cameras) is `w = −u_z`; the pressure `p` is
//! positive in compression; the traction `τ` is what the object exerts on the gel. Units: mm and
//! kPa, so a compliance is in mm / kPa per unit of transformed traction.

use crate::error::{Result, invalid};

/// The elastic layer's facts: what the contact mechanics needs of the gel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Layer {
    /// Thickness of the elastomer between the contact surface and the rigid plate, mm.
    pub thickness_mm: f64,
    /// Young's modulus, kPa.
    pub modulus_kpa: f64,
    /// Poisson's ratio, in [0, 0.5).
    pub poisson: f64,
}

impl Layer {
    /// The reference sensor's gel: 2.5 mm of silicone (150 kPa, Poisson ratio 0.45) bonded to its
    /// acrylic window (`calib/reference-sensor.json`, the pipeline's default).
    pub const REFERENCE: Self = Self {
        thickness_mm: 2.5,
        modulus_kpa: 150.0,
        poisson: 0.45,
    };

    /// Checks the three facts: a positive finite thickness and modulus and a Poisson ratio in
    /// [0, 0.5) (0.5, the incompressible limit, makes a bonded layer rigid under uniform load).
    pub fn validate(&self) -> Result<()> {
        let positive = |field: &'static str, v: f64, unit: &str| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(invalid(field, &format!("a positive, finite {unit}"), v))
            }
        };
        positive("thickness_mm", self.thickness_mm, "thickness in mm")?;
        positive("modulus_kpa", self.modulus_kpa, "Young's modulus in kPa")?;
        if !(self.poisson.is_finite() && (0.0..0.5).contains(&self.poisson)) {
            return Err(invalid("poisson", "a Poisson ratio in [0, 0.5)", self.poisson));
        }
        Ok(())
    }

    /// Shear modulus μ, kPa.
    pub fn shear_modulus_kpa(&self) -> f64 {
        self.modulus_kpa / (2.0 * (1.0 + self.poisson))
    }

    /// Plane-strain modulus `E* = E / (1 − ν²)`, kPa.
    pub fn plane_strain_modulus_kpa(&self) -> f64 {
        self.modulus_kpa / (1.0 - self.poisson * self.poisson)
    }

    /// The surface compliance at wave number `k` (rad / mm, `k >= 0`).
    pub fn compliance(&self, k: f64) -> Compliance {
        let (h, nu, mu) = (self.thickness_mm, self.poisson, self.shear_modulus_kpa());
        let x = k * h;
        if x < 1e-9 {
            return Compliance {
                normal: h * (1.0 - 2.0 * nu) / (2.0 * mu * (1.0 - nu)),
                longitudinal: h / mu,
                transverse: h / mu,
                coupling: 0.0,
            };
        }
        let s = (-2.0 * x).exp();
        let kappa = 3.0 - 4.0 * nu;
        let d = kappa * (1.0 + s * s) + (4.0 * x * x + kappa * kappa + 1.0) * s;
        let mk = mu * k;
        Compliance {
            normal: (1.0 - nu) * (kappa * (1.0 - s * s) - 4.0 * x * s) / (mk * d),
            longitudinal: (1.0 - nu) * (kappa * (1.0 - s * s) + 4.0 * x * s) / (mk * d),
            transverse: (1.0 - s) / ((1.0 + s) * mk),
            coupling: (4.0 * x * x * s - (1.0 - 2.0 * nu) * kappa * (1.0 - s) * (1.0 - s)) / (2.0 * mk * d),
        }
    }
}

/// The layer's surface compliance at one wave number (see the module's documentation), mm / kPa
/// per unit of transformed traction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Compliance {
    /// Pressure to displacement into the gel.
    pub normal: f64,
    /// Traction along the wave vector to displacement along it.
    pub longitudinal: f64,
    /// Traction across the wave vector to displacement across it.
    pub transverse: f64,
    /// Traction along the wave vector to displacement into the gel, times `−i` (and pressure to
    /// displacement along the wave vector, times `i`).
    pub coupling: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    const GEL: Layer = Layer {
        thickness_mm: 2.0,
        modulus_kpa: 120.0,
        poisson: 0.45,
    };

    #[test]
    fn a_thick_layer_is_a_half_space_and_a_long_wave_strains_the_layer_uniformly() {
        let mu = GEL.shear_modulus_kpa();
        let nu = GEL.poisson;
        let k = 40.0 / GEL.thickness_mm;
        let c = GEL.compliance(k);
        let close = |a: f64, b: f64| (a - b).abs() < 1e-9 * b.abs().max(1e-12);
        assert!(close(c.normal, (1.0 - nu) / (mu * k)));
        assert!(close(c.longitudinal, (1.0 - nu) / (mu * k)));
        assert!(close(c.transverse, 1.0 / (mu * k)));
        assert!(close(c.coupling, -(1.0 - 2.0 * nu) / (2.0 * mu * k)));
        // Long waves: the exact limits, reached continuously.
        let c0 = GEL.compliance(0.0);
        let c1 = GEL.compliance(1e-5 / GEL.thickness_mm);
        let uniaxial = GEL.thickness_mm * (1.0 - 2.0 * nu) / (2.0 * mu * (1.0 - nu));
        assert!(close(c0.normal, uniaxial) && (c1.normal - uniaxial).abs() < 1e-6 * uniaxial);
        assert!((c1.longitudinal - GEL.thickness_mm / mu).abs() < 1e-6 * c1.longitudinal);
        assert!((c1.transverse - GEL.thickness_mm / mu).abs() < 1e-6 * c1.transverse);
        assert!(c1.coupling.abs() < 1e-4 * c1.normal);
    }

    #[test]
    fn the_compliance_is_positive_definite_at_every_wave_number() {
        for nu in [0.0, 0.3, 0.45, 0.499] {
            let gel = Layer { poisson: nu, ..GEL };
            for i in 0..400 {
                let k = 1e-3 * 1.05f64.powi(i);
                let c = gel.compliance(k);
                // The 2 x 2 block (longitudinal, normal) with off-diagonal ±i·coupling.
                assert!(c.normal > 0.0 && c.transverse > 0.0, "nu {nu} k {k}: {c:?}");
                assert!(
                    c.normal * c.longitudinal > c.coupling * c.coupling,
                    "nu {nu} k {k}: {c:?}"
                );
            }
        }
    }

    #[test]
    fn bad_facts_are_named() {
        for (gel, field) in [
            (
                Layer {
                    thickness_mm: 0.0,
                    ..GEL
                },
                "thickness_mm",
            ),
            (
                Layer {
                    modulus_kpa: f64::NAN,
                    ..GEL
                },
                "modulus_kpa",
            ),
            (Layer { poisson: 0.5, ..GEL }, "poisson"),
            (Layer { poisson: -0.1, ..GEL }, "poisson"),
        ] {
            let e = gel.validate().unwrap_err().to_string();
            assert!(e.contains(field), "{e}");
        }
        GEL.validate().unwrap();
    }
}
