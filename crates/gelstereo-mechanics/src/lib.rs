//! Contact mechanics of a tactile sensor's gel: an elastic layer bonded to a rigid plate.
//!
//! - [`Layer`]: the gel's facts (thickness, Young's modulus, Poisson ratio) and its exact surface
//!   compliance in Fourier space.
//! - [`Influence`]: the layer's response on a square lattice (cells of uniform traction, nodes
//!   where the displacement is read), applied by FFT.
//! - [`inverse`]: the tractions (pressure `p >= 0`, shear inside the friction cone's
//!   closure) that explain measured 3-D surface displacements, and what follows from them:
//!   contact region, area, force, shear, torque, centroid.
//! - [`forward`]: the displacements of the layer pressed by a rigid frictionless indenter (the
//!   simulator's normal contact, and the analytic checks).

pub mod error;
pub mod forward;
pub mod influence;
pub mod inverse;
pub mod layer;

pub use error::{Error, Result};
pub use influence::{Influence, Vec3, Workspace};
pub use layer::{Compliance, Layer};
