//! A rectangle of an image in original pixels: where the closer look ran, which the lattice check and
//! the blob searches read.

use gelstereo_core::{Detection, ImageSize};

/// A rectangle of an image, original px (pixel-centre convention), edges included.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Region {
    /// Left edge.
    pub x0: f64,
    /// Top edge.
    pub y0: f64,
    /// Right edge.
    pub x1: f64,
    /// Bottom edge.
    pub y1: f64,
}

impl Region {
    /// Whether `d` lies inside (edges included).
    pub fn contains(&self, d: &Detection) -> bool {
        (self.x0..=self.x1).contains(&d.position.x) && (self.y0..=self.y1).contains(&d.position.y)
    }

    /// Its share of an image of `size`.
    pub fn share_of(&self, size: ImageSize) -> f64 {
        let area = f64::from(size.width) * f64::from(size.height);
        ((self.x1 - self.x0).max(0.0) * (self.y1 - self.y0).max(0.0)) / area.max(1.0)
    }
}
