//! The gel's Young's modulus found from presses of known force (`gelstereo calibrate-gel`).
//!
//! With the thickness and Poisson ratio fixed, the layer is linear: the
//! tractions that explain given displacements scale with Young's modulus, and so does every force
//! the pipeline reports. Tracking a press of known force with an assumed modulus `E0` and getting
//! forces `F̂` where the truth is `F`, the modulus is `E = E0 · Σ F F̂ / Σ F̂²` (least squares over
//! the frames in contact).

use gelstereo::{Error, Result};

/// A modulus fitted to presses of known force.
#[derive(Debug, Clone, PartialEq)]
pub struct ModulusFit {
    /// The fitted Young's modulus, kPa.
    pub modulus_kpa: f64,
    /// The frames used (in contact, with a known force).
    pub frames: usize,
    /// The per-frame moduli `E0 F / F̂`: their quartiles, kPa (how well one modulus explains all).
    pub quartiles_kpa: [f64; 3],
}

/// Fits the modulus from `(known force, estimated force)` pairs, N, estimated with the modulus
/// `assumed_kpa`; pairs whose estimate or truth is not positive are skipped.
pub fn fit_modulus(assumed_kpa: f64, pairs: &[(f64, f64)]) -> Result<ModulusFit> {
    let used: Vec<(f64, f64)> = pairs
        .iter()
        .copied()
        .filter(|(f, e)| f.is_finite() && e.is_finite() && *f > 0.0 && *e > 0.0)
        .collect();
    if used.is_empty() {
        return Err(Error::Invalid(
            "no frame in contact with a known force: expected a press the pipeline sees as contact, and a positive force"
                .into(),
        ));
    }
    let (num, den) = used
        .iter()
        .fold((0.0, 0.0), |(n, d), (f, e)| (n + f * e, d + e * e));
    let mut per_frame: Vec<f64> = used.iter().map(|(f, e)| assumed_kpa * f / e).collect();
    per_frame.sort_by(f64::total_cmp);
    let at = |q: f64| per_frame[((per_frame.len() - 1) as f64 * q).round() as usize];
    Ok(ModulusFit {
        modulus_kpa: assumed_kpa * num / den,
        frames: used.len(),
        quartiles_kpa: [at(0.25), at(0.5), at(0.75)],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_modulus_scales_the_force() {
        // Forces estimated with 100 kPa where the gel is 150 kPa come out 1.5 x too small.
        let pairs = [(0.3, 0.2), (0.6, 0.4), (0.9, 0.6), (0.0, 0.0), (0.5, 0.0)];
        let fit = fit_modulus(100.0, &pairs).unwrap();
        assert!(
            (fit.modulus_kpa - 150.0).abs() < 1e-9 && fit.frames == 3,
            "{fit:?}"
        );
        assert!(
            fit_modulus(100.0, &[(0.0, 0.1)])
                .unwrap_err()
                .to_string()
                .contains("no frame")
        );
    }
}
