//! The layer's influence operator on a square lattice: the displacement of every node under a
//! traction that is uniform over each node's square cell, as a convolution applied by FFT.
//!
//! The stencils (displacement at node offsets from one loaded cell) come from the Fourier-space
//! compliance of [`Layer`] times the cell's transform, inverted on a grid `OVERSAMPLING` times
//! finer than the lattice and sampled at the nodes. The compliance falls as `1/|k|` and the
//! cell's transform as `1/|k|` along the axes, so cutting the spectrum at the fine grid's
//! Nyquist frequency leaves an error proportional to the fine spacing; two fine grids (`q` and
//! `2q`) and a Richardson step remove its first order. A bonded layer's response decays within a
//! few thicknesses, so the stencils are cut where they fall below `STENCIL_TAIL` of the largest
//! entry and the lattice is padded by that radius: the FFT's circular convolution then equals
//! the linear one on the lattice.

use std::sync::Arc;

use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::num_complex::Complex64;
use rustfft::{Fft, FftPlanner};

use crate::error::{Result, invalid};
use crate::layer::Layer;

/// The finer of the two grids the stencils are computed on, in grid steps per lattice step.
const OVERSAMPLING: usize = 16;
/// Stencil entries below this fraction of the largest (the self-compliance) are dropped.
const STENCIL_TAIL: f64 = 2e-4;
/// The largest stencil radius, lattice steps (a thick layer on a fine lattice is cut there).
const MAX_RADIUS: usize = 96;

/// The six distinct entries of the symmetric 3 x 3 operator, in this order: `ux<-τx`, `uy<-τy`,
/// `ux<-τy` (= `uy<-τx`), `w<-p`, `w<-τx` (= `−ux<-p`), `w<-τy` (= `−uy<-p`).
const ENTRIES: usize = 6;

/// The influence operator of a layer on a `rows x cols` lattice of spacing `spacing_mm`.
///
/// The fields are real, so only half of each spectrum is kept: the padded rows go through
/// real-to-complex FFTs (`nc / 2 + 1` frequencies of `nc`), then the columns through complex ones.
/// The spectra are stored column by column (index `j * nr + i` for column frequency `j` and row
/// frequency `i`) so that every column FFT runs on contiguous memory.
#[derive(Clone)]
pub struct Influence {
    rows: usize,
    cols: usize,
    spacing_mm: f64,
    radius: usize,
    /// Padded FFT size (rows, cols); the columns' count is even (a real FFT of even length is
    /// a complex one of half the length).
    size: (usize, usize),
    /// Transformed stencils per frequency of the half spectrum.
    spectrum: Vec<[Complex64; ENTRIES]>,
    /// The largest eigenvalue of the operator over all frequencies, mm / kPa.
    norm: f64,
    /// See [`Influence::pressure_row_norms`].
    pressure_row_norms: (f64, f64),
    row_fft: Arc<dyn RealToComplex<f64>>,
    row_ifft: Arc<dyn ComplexToReal<f64>>,
    col_fft: Arc<dyn Fft<f64>>,
    col_ifft: Arc<dyn Fft<f64>>,
}

impl std::fmt::Debug for Influence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Influence")
            .field("rows", &self.rows)
            .field("cols", &self.cols)
            .field("spacing_mm", &self.spacing_mm)
            .field("radius", &self.radius)
            .field("size", &self.size)
            .finish_non_exhaustive()
    }
}

/// Per-node vectors of the operator: `[x, y, normal]` (traction `[τx, τy, p]` in kPa, or
/// displacement `[ux, uy, w]` in mm).
pub type Vec3 = [f64; 3];

impl Influence {
    /// Builds the operator of `layer` on a `rows x cols` lattice of spacing `spacing_mm`.
    pub fn new(layer: &Layer, rows: usize, cols: usize, spacing_mm: f64) -> Result<Self> {
        layer.validate()?;
        if rows == 0 || cols == 0 || rows > 4096 || cols > 4096 {
            return Err(invalid(
                "lattice",
                "1 to 4096 rows and columns",
                format!("{rows} x {cols}"),
            ));
        }
        if !(spacing_mm.is_finite() && spacing_mm > 0.0) {
            return Err(invalid(
                "pitch_mm",
                "a positive, finite lattice pitch in mm",
                spacing_mm,
            ));
        }
        let radius = stencil_radius(layer, spacing_mm);
        let fine = stencils(layer, spacing_mm, radius, OVERSAMPLING);
        let coarse = stencils(layer, spacing_mm, radius, OVERSAMPLING / 2);
        let stencil: Vec<[f64; ENTRIES]> = fine
            .iter()
            .zip(&coarse)
            .map(|(f, c)| std::array::from_fn(|e| 2.0 * f[e] - c[e]))
            .collect();
        // The circular convolution equals the linear one on the lattice when the period exceeds
        // the lattice by the stencil's radius.
        let size = (
            fft_size(rows + radius + 1, false),
            fft_size(cols + radius + 1, true),
        );
        let mut planner = FftPlanner::new();
        let mut real_planner = RealFftPlanner::new();
        let mut op = Self {
            rows,
            cols,
            spacing_mm,
            radius,
            size,
            spectrum: Vec::new(),
            norm: 0.0,
            pressure_row_norms: (0.0, 0.0),
            row_fft: real_planner.plan_fft_forward(size.1),
            row_ifft: real_planner.plan_fft_inverse(size.1),
            col_fft: planner.plan_fft_forward(size.0),
            col_ifft: planner.plan_fft_inverse(size.0),
        };
        op.spectrum = op.transform_stencil(&stencil);
        op.norm = op.spectrum.iter().map(largest_eigenvalue).fold(0.0, f64::max);
        op.pressure_row_norms = op.mean_pressure_rows();
        Ok(op)
    }

    /// Lattice rows.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Lattice columns.
    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Lattice spacing, mm.
    pub fn spacing_mm(&self) -> f64 {
        self.spacing_mm
    }

    /// Stencil radius, lattice steps.
    pub fn radius(&self) -> usize {
        self.radius
    }

    /// The operator's largest eigenvalue, mm / kPa (the step bound of gradient methods).
    pub fn norm(&self) -> f64 {
        self.norm
    }

    /// The Euclidean norms of the pressure's row of the operator: its normal entries (`w<-p`)
    /// and its tangential ones (`ux, uy <- p`), mm / kPa. Noise of standard deviation σ in the
    /// normal (tangential) displacements reaches the pressure's gradient `(C u)_p` with standard
    /// deviation σ times the first (second).
    pub fn pressure_row_norms(&self) -> (f64, f64) {
        self.pressure_row_norms
    }

    /// The means over the full spectrum behind [`pressure_row_norms`](Self::pressure_row_norms):
    /// a column frequency of the half spectrum stands for itself and its negative, except the
    /// zero and (even size) Nyquist ones, which are their own negatives.
    fn mean_pressure_rows(&self) -> (f64, f64) {
        let (nr, nc) = self.size;
        let (normal, tangential) =
            self.spectrum
                .chunks(nr)
                .enumerate()
                .fold((0.0, 0.0), |(n, t), (j, column)| {
                    let weight = if j == 0 || 2 * j == nc { 1.0 } else { 2.0 };
                    let (cn, ct) = column.iter().fold((0.0, 0.0), |(n, t), s| {
                        (n + s[3].norm_sqr(), t + s[4].norm_sqr() + s[5].norm_sqr())
                    });
                    (n + weight * cn, t + weight * ct)
                });
        let count = (nr * nc) as f64;
        ((normal / count).sqrt(), (tangential / count).sqrt())
    }

    /// `out = C t`: the displacement of every node under the tractions `t` (row-major over the
    /// lattice). `work` is scratch space, resized as needed.
    pub fn apply(&self, t: &[Vec3], out: &mut [Vec3], work: &mut Workspace) {
        self.transform(t, work);
        let [px, py, pn] = &mut work.planes;
        for (k, s) in self.spectrum.iter().enumerate() {
            let v = operator(s).mul([px[k], py[k], pn[k]]);
            (px[k], py[k], pn[k]) = (v[0], v[1], v[2]);
        }
        self.untransform(work, out);
    }

    /// The operator's 3 x 3 matrix at each frequency of the half spectrum, acting on
    /// `[τx, τy, p]`.
    pub(crate) fn matrices(&self) -> impl Iterator<Item = Matrix3> + '_ {
        self.spectrum.iter().map(operator)
    }

    /// Zero-pads the three components of `t` and transforms them into `work`'s planes.
    pub(crate) fn transform(&self, t: &[Vec3], work: &mut Workspace) {
        assert!(t.len() == self.rows * self.cols, "fields must cover the lattice");
        work.resize(self);
        let Workspace {
            planes,
            row,
            row_spectrum,
            scratch,
        } = work;
        for (c, plane) in planes.iter_mut().enumerate() {
            self.forward(
                (self.rows, self.cols),
                |k| t[k][c],
                plane,
                row,
                row_spectrum,
                scratch,
            );
        }
    }

    /// Inverse of [`transform`](Self::transform): `work`'s planes back to the lattice (the
    /// planes are left as scratch).
    pub(crate) fn untransform(&self, work: &mut Workspace, out: &mut [Vec3]) {
        assert!(
            out.len() == self.rows * self.cols,
            "fields must cover the lattice"
        );
        let (nr, nc) = self.size;
        let scale = 1.0 / (nr * nc) as f64;
        let Workspace {
            planes,
            row,
            row_spectrum,
            scratch,
        } = work;
        for (c, plane) in planes.iter_mut().enumerate() {
            run_fft(&*self.col_ifft, plane, scratch);
            for r in 0..self.rows {
                for (j, z) in row_spectrum.iter_mut().enumerate() {
                    *z = plane[j * nr + r];
                }
                // The field is real: the zero and Nyquist frequencies' imaginary parts are
                // rounding only.
                row_spectrum[0].im = 0.0;
                if let Some(last) = row_spectrum.last_mut() {
                    last.im = 0.0;
                }
                self.row_ifft
                    .process_with_scratch(row_spectrum, row, scratch)
                    .unwrap_or_else(|e| unreachable!("buffers sized by the plan: {e}"));
                for (q, v) in row[..self.cols].iter().enumerate() {
                    out[r * self.cols + q][c] = v * scale;
                }
            }
        }
    }

    /// The half spectrum of the real field `value` (row-major over `height x width`, zero-padded
    /// to the FFT size) into `plane`.
    fn forward(
        &self,
        (height, width): (usize, usize),
        value: impl Fn(usize) -> f64,
        plane: &mut [Complex64],
        row: &mut [f64],
        row_spectrum: &mut [Complex64],
        scratch: &mut Vec<Complex64>,
    ) {
        let nr = self.size.0;
        for r in 0..height {
            for (q, v) in row.iter_mut().enumerate() {
                *v = if q < width { value(r * width + q) } else { 0.0 };
            }
            self.row_fft
                .process_with_scratch(row, row_spectrum, scratch)
                .unwrap_or_else(|e| unreachable!("buffers sized by the plan: {e}"));
            for (j, z) in row_spectrum.iter().enumerate() {
                plane[j * nr + r] = *z;
            }
        }
        for column in plane.chunks_mut(nr) {
            column[height..].fill(Complex64::new(0.0, 0.0));
        }
        run_fft(&*self.col_fft, plane, scratch);
    }

    /// The half spectrum of the stencils (offsets wrapped around the padded grid).
    fn transform_stencil(&self, stencil: &[[f64; ENTRIES]]) -> Vec<[Complex64; ENTRIES]> {
        let (nr, nc) = self.size;
        let r = self.radius as isize;
        let side = 2 * self.radius + 1;
        let mut wrapped = vec![[0.0; ENTRIES]; nr * nc];
        for dy in -r..=r {
            for dx in -r..=r {
                let at = dy.rem_euclid(nr as isize) as usize * nc + dx.rem_euclid(nc as isize) as usize;
                wrapped[at] = stencil[(dy + r) as usize * side + (dx + r) as usize];
            }
        }
        let mut work = Workspace::default();
        work.resize(self);
        let Workspace {
            planes,
            row,
            row_spectrum,
            scratch,
        } = &mut work;
        let mut spectra = vec![[Complex64::new(0.0, 0.0); ENTRIES]; planes[0].len()];
        for e in 0..ENTRIES {
            self.forward(
                (nr, nc),
                |k| wrapped[k][e],
                &mut planes[0],
                row,
                row_spectrum,
                scratch,
            );
            for (s, z) in spectra.iter_mut().zip(&planes[0]) {
                s[e] = *z;
            }
        }
        spectra
    }
}

/// Scratch buffers of [`Influence::apply`].
#[derive(Debug, Clone, Default)]
pub struct Workspace {
    /// The three components' half spectra.
    pub(crate) planes: [Vec<Complex64>; 3],
    /// One padded row and its half spectrum.
    row: Vec<f64>,
    row_spectrum: Vec<Complex64>,
    scratch: Vec<Complex64>,
}

/// A complex 3 x 3 matrix, row-major.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Matrix3(pub(crate) [[Complex64; 3]; 3]);

impl Matrix3 {
    pub(crate) fn mul(&self, v: [Complex64; 3]) -> [Complex64; 3] {
        std::array::from_fn(|r| self.0[r][0] * v[0] + self.0[r][1] * v[1] + self.0[r][2] * v[2])
    }

    pub(crate) fn mul_matrix(&self, o: &Matrix3) -> Matrix3 {
        Matrix3(std::array::from_fn(|r| {
            std::array::from_fn(|c| (0..3).map(|k| self.0[r][k] * o.0[k][c]).sum())
        }))
    }

    /// The inverse, by cofactors (the matrices inverted here are Hermitian and well conditioned).
    pub(crate) fn inverse(&self) -> Matrix3 {
        let m = &self.0;
        let cof = |r: usize, c: usize| {
            let (r0, r1) = ((r + 1) % 3, (r + 2) % 3);
            let (c0, c1) = ((c + 1) % 3, (c + 2) % 3);
            m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0]
        };
        let det = m[0][0] * cof(0, 0) + m[0][1] * cof(0, 1) + m[0][2] * cof(0, 2);
        Matrix3(std::array::from_fn(|r| std::array::from_fn(|c| cof(c, r) / det)))
    }
}

/// The operator's matrix at one frequency from its six distinct transformed stencils: the
/// `w<-τ` entries are imaginary (odd stencils) and `u<-p` is their negative, so the matrix is
/// Hermitian.
fn operator(s: &[Complex64; ENTRIES]) -> Matrix3 {
    Matrix3([[s[0], s[2], -s[4]], [s[2], s[1], -s[5]], [s[4], s[5], s[3]]])
}

impl Workspace {
    fn resize(&mut self, op: &Influence) {
        let (nr, nc) = op.size;
        let half = nc / 2 + 1;
        for p in &mut self.planes {
            p.resize(nr * half, Complex64::new(0.0, 0.0));
        }
        self.row.resize(nc, 0.0);
        self.row_spectrum.resize(half, Complex64::new(0.0, 0.0));
        let need = [
            op.row_fft.get_scratch_len(),
            op.row_ifft.get_scratch_len(),
            op.col_fft.get_inplace_scratch_len(),
            op.col_ifft.get_inplace_scratch_len(),
        ]
        .into_iter()
        .max()
        .unwrap_or(0);
        if self.scratch.len() < need {
            self.scratch.resize(need, Complex64::new(0.0, 0.0));
        }
    }
}

/// Largest eigenvalue of the Hermitian 3 x 3 matrix of one frequency (bounded by its largest
/// absolute row sum, which is enough for a step size).
fn largest_eigenvalue(s: &[Complex64; ENTRIES]) -> f64 {
    let rows = [
        s[0].norm() + s[2].norm() + s[4].norm(),
        s[2].norm() + s[1].norm() + s[5].norm(),
        s[4].norm() + s[5].norm() + s[3].norm(),
    ];
    rows.into_iter().fold(0.0, f64::max)
}

/// The smallest size >= `n` with no prime factor above 5 (fast FFT sizes), even if `even`.
fn fft_size(n: usize, even: bool) -> usize {
    (n..)
        .find(|&m| {
            if even && m % 2 == 1 {
                return false;
            }
            let mut m = m;
            for p in [2, 3, 5] {
                while m % p == 0 {
                    m /= p;
                }
            }
            m == 1
        })
        .unwrap_or(n)
}

/// Every line of `buf` through `fft`, with its scratch space taken from `scratch` (grown once, not
/// allocated per call: the lattice's FFTs are small and run tens of times a frame).
fn run_fft(fft: &dyn Fft<f64>, buf: &mut [Complex64], scratch: &mut Vec<Complex64>) {
    let need = fft.get_inplace_scratch_len();
    if scratch.len() < need {
        scratch.resize(need, Complex64::new(0.0, 0.0));
    }
    fft.process_with_scratch(buf, &mut scratch[..need]);
}

fn transpose(src: &[Complex64], rows: usize, cols: usize, dst: &mut Vec<Complex64>) {
    dst.resize(src.len(), Complex64::new(0.0, 0.0));
    for r in 0..rows {
        for c in 0..cols {
            dst[c * rows + r] = src[r * cols + c];
        }
    }
}

/// The radius (lattice steps) beyond which the layer's normal response to a loaded cell stays
/// below `STENCIL_TAIL` of its self-response, from a coarse look at the response along an axis.
fn stencil_radius(layer: &Layer, spacing_mm: f64) -> usize {
    // A first pass at a generous radius, then cut where every entry has decayed.
    let generous = ((6.0 * layer.thickness_mm / spacing_mm).ceil() as usize).clamp(4, MAX_RADIUS);
    let s = stencils(layer, spacing_mm, generous, 4);
    let side = 2 * generous + 1;
    let peak = s
        .iter()
        .flat_map(|e| e.iter())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let mut radius = 1;
    for (i, e) in s.iter().enumerate() {
        let (dy, dx) = ((i / side).abs_diff(generous), (i % side).abs_diff(generous));
        if e.iter().any(|v| v.abs() > STENCIL_TAIL * peak) {
            radius = radius.max(dx.max(dy));
        }
    }
    radius.min(generous)
}

/// The six stencils at offsets `[-radius, radius]^2` (row-major), from the spectrum sampled on
/// a grid `q` times finer than the lattice spanning a period of `2 radius + 2` lattice steps.
/// Only the lattice nodes are wanted, and `e^(i k x)` at a node depends on the frequency index
/// modulo the period in lattice steps, so the fine spectrum is folded onto the lattice's
/// frequencies (its aliases summed) and one small inverse FFT gives the nodes.
fn stencils(layer: &Layer, a: f64, radius: usize, q: usize) -> Vec<[f64; ENTRIES]> {
    let period = 2 * radius + 2;
    let m = period * q;
    let period_mm = period as f64 * a;
    let dk = 2.0 * std::f64::consts::PI / period_mm;
    let freq = |i: usize| if i <= m / 2 { i as f64 } else { i as f64 - m as f64 } * dk;
    let sinc = |v: f64| if v.abs() < 1e-12 { 1.0 } else { v.sin() / v };
    let mut planes = vec![vec![Complex64::new(0.0, 0.0); period * period]; ENTRIES];
    for iy in 0..m {
        let ky = freq(iy);
        for ix in 0..m {
            let kx = freq(ix);
            let k = kx.hypot(ky);
            let c = layer.compliance(k);
            // At k = 0 the direction is undefined and the tangential response isotropic
            // (longitudinal = transverse): any unit direction gives it.
            let (ux, uy) = if k > 0.0 { (kx / k, ky / k) } else { (1.0, 0.0) };
            let cell = a * a * sinc(0.5 * kx * a) * sinc(0.5 * ky * a);
            let at = (iy % period) * period + ix % period;
            planes[0][at].re += (c.longitudinal * ux * ux + c.transverse * uy * uy) * cell;
            planes[1][at].re += (c.longitudinal * uy * uy + c.transverse * ux * ux) * cell;
            planes[2][at].re += (c.longitudinal - c.transverse) * ux * uy * cell;
            planes[3][at].re += c.normal * cell;
            planes[4][at].im += c.coupling * ux * cell;
            planes[5][at].im += c.coupling * uy * cell;
        }
    }
    let ifft = FftPlanner::new().plan_fft_inverse(period);
    let mut scratch = Vec::new();
    let scale = 1.0 / (period_mm * period_mm);
    for plane in &mut planes {
        ifft.process(plane);
        transpose(plane, period, period, &mut scratch);
        plane.copy_from_slice(&scratch);
        ifft.process(plane);
    }
    // `planes` is now transposed: index [x * period + y].
    let side = 2 * radius + 1;
    let mut out = vec![[0.0; ENTRIES]; side * side];
    let r = radius as isize;
    for dy in -r..=r {
        for dx in -r..=r {
            let at =
                dx.rem_euclid(period as isize) as usize * period + dy.rem_euclid(period as isize) as usize;
            let o = &mut out[(dy + r) as usize * side + (dx + r) as usize];
            for (e, v) in o.iter_mut().enumerate() {
                *v = planes[e][at].re * scale;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const GEL: Layer = Layer::REFERENCE;

    /// A uniform pressure over a wide patch of a bonded layer compresses it uniaxially in the
    /// middle: `w = p h (1+ν)(1−2ν) / E(1−ν)`.
    #[test]
    fn a_wide_uniform_pressure_compresses_the_layer_uniaxially() {
        let (rows, cols, a) = (61, 61, 0.5);
        let op = Influence::new(&GEL, rows, cols, a).unwrap();
        let p = 10.0;
        let t = vec![[0.0, 0.0, p]; rows * cols];
        let mut u = vec![[0.0; 3]; rows * cols];
        op.apply(&t, &mut u, &mut Workspace::default());
        let nu = GEL.poisson;
        let want = p * GEL.thickness_mm * (1.0 + nu) * (1.0 - 2.0 * nu) / (GEL.modulus_kpa * (1.0 - nu));
        let centre = u[30 * cols + 30];
        assert!((centre[2] - want).abs() < 0.01 * want, "{centre:?} vs {want}");
        assert!(centre[0].abs() < 1e-9 && centre[1].abs() < 1e-9);
    }

    /// A uniform shear over a wide patch shears the layer simply: `u = τ h / μ`.
    #[test]
    fn a_wide_uniform_shear_shears_the_layer_simply() {
        let (rows, cols, a) = (61, 61, 0.5);
        let op = Influence::new(&GEL, rows, cols, a).unwrap();
        let t = vec![[3.0, -1.0, 0.0]; rows * cols];
        let mut u = vec![[0.0; 3]; rows * cols];
        op.apply(&t, &mut u, &mut Workspace::default());
        let mu = GEL.shear_modulus_kpa();
        let c = u[30 * cols + 30];
        let h = GEL.thickness_mm;
        assert!((c[0] - 3.0 * h / mu).abs() < 0.01 * 3.0 * h / mu, "{c:?}");
        assert!((c[1] + h / mu).abs() < 0.01 * h / mu, "{c:?}");
        assert!(c[2].abs() < 0.01 * h / mu, "{c:?}");
    }

    /// Reciprocity: the operator is symmetric (`<C s, t> = <s, C t>`).
    #[test]
    fn the_operator_is_symmetric() {
        let (rows, cols) = (13, 17);
        let op = Influence::new(&GEL, rows, cols, 0.8).unwrap();
        let field = |seed: u64| -> Vec<Vec3> {
            let mut x = seed;
            (0..rows * cols)
                .map(|_| {
                    std::array::from_fn(|_| {
                        x ^= x << 13;
                        x ^= x >> 7;
                        x ^= x << 17;
                        (x % 1000) as f64 / 500.0 - 1.0
                    })
                })
                .collect()
        };
        let (s, t) = (field(7), field(11));
        let mut cs = vec![[0.0; 3]; rows * cols];
        let mut ct = vec![[0.0; 3]; rows * cols];
        let mut work = Workspace::default();
        op.apply(&s, &mut cs, &mut work);
        op.apply(&t, &mut ct, &mut work);
        let dot = |a: &[Vec3], b: &[Vec3]| -> f64 {
            a.iter()
                .zip(b)
                .map(|(x, y)| x[0] * y[0] + x[1] * y[1] + x[2] * y[2])
                .sum()
        };
        let (l, r) = (dot(&cs, &t), dot(&s, &ct));
        assert!((l - r).abs() < 1e-9 * l.abs().max(r.abs()), "{l} vs {r}");
    }
}
