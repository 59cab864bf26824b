//! Indenter shapes: rigid objects pressed into the gel, each described by its height above its
//! lowest point as a function of the position under it (local frame, mm).
//!
//! Flat-faced objects (punches, stars, nuts, text) have a small edge fillet so the contact edge is
//! sharp but not a cliff.

use rand::Rng;
use serde::{Deserialize, Serialize};

/// An indenter: its shape and the deepest press the scripts use with it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case")]
pub enum Indenter {
    /// A sphere pressed pole first.
    Sphere {
        /// Radius, mm.
        radius_mm: f64,
    },
    /// A cylinder pressed flat end first (flat punch).
    FlatCylinder {
        /// Radius, mm.
        radius_mm: f64,
    },
    /// A cylinder lying on its side, axis along local x.
    SideCylinder {
        /// Radius, mm.
        radius_mm: f64,
        /// Length, mm.
        length_mm: f64,
    },
    /// The edge of a cube (two faces at 45 degrees), along local x.
    CubeEdge {
        /// Edge length in contact, mm.
        length_mm: f64,
    },
    /// A cube's corner, pressed along its body diagonal.
    CubeCorner,
    /// A cone pressed tip first.
    Cone {
        /// Half opening angle, degrees.
        half_angle_deg: f64,
    },
    /// A triangular prism pressed end face first.
    Prism {
        /// Side of the triangle, mm.
        side_mm: f64,
    },
    /// A hexagonal prism pressed end face first.
    Hexagon {
        /// Circumradius, mm.
        radius_mm: f64,
    },
    /// A five-pointed star, flat face first.
    Star {
        /// Outer radius, mm.
        radius_mm: f64,
    },
    /// A plus-shaped cross, flat face first.
    Cross {
        /// Arm length from the centre, mm.
        arm_mm: f64,
        /// Arm width, mm.
        width_mm: f64,
    },
    /// A hexagonal nut (ring contact), flat face first.
    Nut {
        /// Circumradius of the hexagon, mm.
        radius_mm: f64,
        /// Radius of the hole, mm.
        hole_mm: f64,
    },
    /// A flat block with a groove across it (two parallel contact strips).
    Groove {
        /// Block width (across the groove), mm.
        width_mm: f64,
        /// Groove width, mm.
        groove_mm: f64,
    },
    /// Raised letters (stroke font) on a flat stamp.
    Text {
        /// The letters (from `LTHEFXZNIV`).
        text: String,
        /// Letter height, mm.
        height_mm: f64,
    },
    /// A large sphere covered with random bumps.
    Bumpy {
        /// Base sphere radius, mm.
        radius_mm: f64,
        /// Bumps: centre x, centre y, radius, height (mm).
        bumps: Vec<[f64; 4]>,
    },
    /// A fingertip: a soft elongated pad that flattens in contact (ridges are drawn by the
    /// renderer).
    Fingertip {
        /// Radius along local x, mm.
        rx_mm: f64,
        /// Radius along local y, mm.
        ry_mm: f64,
    },
}

/// Every shape name, in the order [`Indenter::random`] cycles through them.
pub const SHAPES: [&str; 15] = [
    "sphere",
    "flat_cylinder",
    "side_cylinder",
    "cube_edge",
    "cube_corner",
    "cone",
    "prism",
    "hexagon",
    "star",
    "cross",
    "nut",
    "groove",
    "text",
    "bumpy",
    "fingertip",
];

const FILLET_MM: f64 = 0.25;

fn fillet(sd: f64) -> f64 {
    // Parabolic fillet of radius FILLET_MM: 0 well inside, rising smoothly across the edge.
    if sd <= -FILLET_MM {
        0.0
    } else {
        let t = sd + FILLET_MM;
        t * t / (2.0 * FILLET_MM)
    }
}

fn sd_polygon(v: &[[f64; 2]], x: f64, y: f64) -> f64 {
    // Signed distance to a simple polygon (negative inside), after Inigo Quilez.
    let n = v.len();
    let dx0 = x - v[0][0];
    let dy0 = y - v[0][1];
    let mut d = dx0 * dx0 + dy0 * dy0;
    let mut s = 1.0;
    let mut j = n - 1;
    for i in 0..n {
        let (ex, ey) = (v[j][0] - v[i][0], v[j][1] - v[i][1]);
        let (wx, wy) = (x - v[i][0], y - v[i][1]);
        let t = ((wx * ex + wy * ey) / (ex * ex + ey * ey)).clamp(0.0, 1.0);
        let (bx, by) = (wx - ex * t, wy - ey * t);
        d = d.min(bx * bx + by * by);
        let c1 = y >= v[i][1];
        let c2 = y < v[j][1];
        let c3 = ex * wy > ey * wx;
        if (c1 && c2 && c3) || (!c1 && !c2 && !c3) {
            s = -s;
        }
        j = i;
    }
    s * d.sqrt()
}

fn regular_polygon(n: usize, r: f64, phase: f64) -> Vec<[f64; 2]> {
    (0..n)
        .map(|k| {
            let a = phase + std::f64::consts::TAU * k as f64 / n as f64;
            [r * a.cos(), r * a.sin()]
        })
        .collect()
}

fn sd_segment(x: f64, y: f64, a: [f64; 2], b: [f64; 2]) -> f64 {
    let (px, py) = (x - a[0], y - a[1]);
    let (bx, by) = (b[0] - a[0], b[1] - a[1]);
    let t = ((px * bx + py * by) / (bx * bx + by * by)).clamp(0.0, 1.0);
    (px - bx * t).hypot(py - by * t)
}

/// Strokes of a tiny font in a unit box (x right, y down, 0..0.6 wide, 0..1 high).
fn glyph(c: char) -> &'static [[f64; 4]] {
    match c {
        'L' => &[[0.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.6, 1.0]],
        'T' => &[[0.0, 0.0, 0.6, 0.0], [0.3, 0.0, 0.3, 1.0]],
        'H' => &[[0.0, 0.0, 0.0, 1.0], [0.6, 0.0, 0.6, 1.0], [0.0, 0.5, 0.6, 0.5]],
        'E' => &[
            [0.0, 0.0, 0.0, 1.0],
            [0.0, 0.0, 0.6, 0.0],
            [0.0, 0.5, 0.45, 0.5],
            [0.0, 1.0, 0.6, 1.0],
        ],
        'F' => &[[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.6, 0.0], [0.0, 0.5, 0.45, 0.5]],
        'X' => &[[0.0, 0.0, 0.6, 1.0], [0.6, 0.0, 0.0, 1.0]],
        'Z' => &[[0.0, 0.0, 0.6, 0.0], [0.6, 0.0, 0.0, 1.0], [0.0, 1.0, 0.6, 1.0]],
        'N' => &[[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.6, 1.0], [0.6, 1.0, 0.6, 0.0]],
        'V' => &[[0.0, 0.0, 0.3, 1.0], [0.3, 1.0, 0.6, 0.0]],
        _ => &[[0.3, 0.0, 0.3, 1.0]],
    }
}

/// Letters [`Indenter::Text`] can draw.
pub const TEXT_LETTERS: &str = "LTHEFXZNIV";

impl Indenter {
    /// The shape's name (one of [`SHAPES`]).
    pub fn name(&self) -> &'static str {
        match self {
            Self::Sphere { .. } => "sphere",
            Self::FlatCylinder { .. } => "flat_cylinder",
            Self::SideCylinder { .. } => "side_cylinder",
            Self::CubeEdge { .. } => "cube_edge",
            Self::CubeCorner => "cube_corner",
            Self::Cone { .. } => "cone",
            Self::Prism { .. } => "prism",
            Self::Hexagon { .. } => "hexagon",
            Self::Star { .. } => "star",
            Self::Cross { .. } => "cross",
            Self::Nut { .. } => "nut",
            Self::Groove { .. } => "groove",
            Self::Text { .. } => "text",
            Self::Bumpy { .. } => "bumpy",
            Self::Fingertip { .. } => "fingertip",
        }
    }

    /// A random indenter of shape `name` (one of [`SHAPES`]), sized for a gel about 18 mm wide
    /// (`scale` multiplies all lengths). `None` for an unknown name.
    pub fn random(name: &str, scale: f64, rng: &mut impl Rng) -> Option<Self> {
        let mut draw = |lo: f64, hi: f64| rng.random_range(lo..hi);
        let len = |mm: f64| mm * scale;
        Some(match name {
            "sphere" => Self::Sphere {
                radius_mm: len([2.0, 3.0, 4.0, 6.0, 8.0][draw(0.0, 5.0) as usize % 5]),
            },
            "flat_cylinder" => Self::FlatCylinder {
                radius_mm: len(draw(1.2, 3.5)),
            },
            "side_cylinder" => Self::SideCylinder {
                radius_mm: len(draw(1.5, 5.0)),
                length_mm: len(draw(6.0, 14.0)),
            },
            "cube_edge" => Self::CubeEdge {
                length_mm: len(draw(5.0, 12.0)),
            },
            "cube_corner" => Self::CubeCorner,
            "cone" => Self::Cone {
                half_angle_deg: draw(35.0, 65.0),
            },
            "prism" => Self::Prism {
                side_mm: len(draw(3.5, 7.0)),
            },
            "hexagon" => Self::Hexagon {
                radius_mm: len(draw(2.0, 4.0)),
            },
            "star" => Self::Star {
                radius_mm: len(draw(3.0, 5.0)),
            },
            "cross" => Self::Cross {
                arm_mm: len(draw(2.5, 4.5)),
                width_mm: len(draw(0.9, 1.6)),
            },
            "nut" => {
                let r = len(draw(2.5, 4.5));
                Self::Nut {
                    radius_mm: r,
                    hole_mm: r * draw(0.45, 0.6),
                }
            }
            "groove" => Self::Groove {
                width_mm: len(draw(4.0, 8.0)),
                groove_mm: len(draw(0.8, 2.0)),
            },
            "text" => {
                let letters: Vec<char> = TEXT_LETTERS.chars().collect();
                let n = 1 + draw(0.0, 3.0) as usize;
                let text = (0..n)
                    .map(|_| letters[draw(0.0, letters.len() as f64) as usize % letters.len()])
                    .collect();
                Self::Text {
                    text,
                    height_mm: len(draw(3.0, 5.0)),
                }
            }
            "bumpy" => {
                let n = 6 + draw(0.0, 10.0) as usize;
                let bumps = (0..n)
                    .map(|_| {
                        [
                            len(draw(-4.0, 4.0)),
                            len(draw(-4.0, 4.0)),
                            len(draw(0.4, 1.2)),
                            len(draw(0.05, 0.35)),
                        ]
                    })
                    .collect();
                Self::Bumpy {
                    radius_mm: len(draw(10.0, 25.0)),
                    bumps,
                }
            }
            "fingertip" => Self::Fingertip {
                rx_mm: len(draw(5.0, 7.0)),
                ry_mm: len(draw(7.0, 10.0)),
            },
            _ => return None,
        })
    }

    /// A sensible range of press depths for this shape, mm (deeper for blunt shapes).
    pub fn depth_range_mm(&self) -> (f64, f64) {
        match self {
            Self::Sphere { radius_mm } => (0.3, (0.25 * radius_mm).clamp(0.6, 1.5)),
            Self::FlatCylinder { .. } | Self::Hexagon { .. } | Self::Prism { .. } => (0.15, 0.6),
            Self::Star { .. } | Self::Cross { .. } | Self::Nut { .. } | Self::Groove { .. } => (0.15, 0.6),
            Self::Text { .. } => (0.15, 0.5),
            Self::SideCylinder { .. } => (0.3, 1.0),
            Self::CubeEdge { .. } | Self::CubeCorner | Self::Cone { .. } => (0.3, 0.9),
            Self::Bumpy { .. } => (0.4, 1.3),
            Self::Fingertip { .. } => (0.4, 1.5),
        }
    }

    /// Height of the indenter's surface above its lowest point at local position (`x`, `y`), mm;
    /// `f64::INFINITY` where it has no surface.
    pub fn height(&self, x: f64, y: f64) -> f64 {
        let r2 = x * x + y * y;
        match self {
            Self::Sphere { radius_mm: r } => {
                if r2 < r * r {
                    r - (r * r - r2).sqrt()
                } else {
                    f64::INFINITY
                }
            }
            Self::FlatCylinder { radius_mm } => fillet(r2.sqrt() - radius_mm),
            Self::SideCylinder {
                radius_mm: r,
                length_mm,
            } => {
                let end = fillet(x.abs() - 0.5 * length_mm);
                if y.abs() < *r {
                    r - (r * r - y * y).sqrt() + end
                } else {
                    f64::INFINITY
                }
            }
            Self::CubeEdge { length_mm } => {
                // Rounded edge (radius 0.2 mm), faces at 45 degrees.
                let re = 0.2;
                (y * y + re * re).sqrt() - re + fillet(x.abs() - 0.5 * length_mm)
            }
            Self::CubeCorner => cube_corner_height(x, y),
            Self::Cone { half_angle_deg } => {
                let slope = 1.0 / half_angle_deg.to_radians().tan();
                let t = 0.2;
                slope * ((r2 + t * t).sqrt() - t)
            }
            Self::Prism { side_mm } => {
                let r = side_mm / 3.0_f64.sqrt();
                fillet(sd_polygon(
                    &regular_polygon(3, r, -std::f64::consts::FRAC_PI_2),
                    x,
                    y,
                ))
            }
            Self::Hexagon { radius_mm } => fillet(sd_polygon(&regular_polygon(6, *radius_mm, 0.0), x, y)),
            Self::Star { radius_mm } => fillet(sd_polygon(&star_polygon(*radius_mm), x, y)),
            Self::Cross { arm_mm: a, width_mm } => {
                let w = 0.5 * width_mm;
                let bx = (x.abs() - a).max(y.abs() - w);
                let by = (x.abs() - w).max(y.abs() - a);
                fillet(bx.min(by))
            }
            Self::Nut { radius_mm, hole_mm } => {
                let hex = sd_polygon(&regular_polygon(6, *radius_mm, 0.0), x, y);
                fillet(hex.max(hole_mm - r2.sqrt()))
            }
            Self::Groove { width_mm, groove_mm } => {
                let outer = (x.abs() - 0.5 * width_mm).max(y.abs() - 0.6 * width_mm);
                fillet(outer.max(0.5 * groove_mm - x.abs()))
            }
            Self::Text { text, height_mm } => text_height(text, *height_mm, x, y),
            Self::Bumpy { radius_mm, bumps } => bumpy_height(*radius_mm, bumps, x, y),
            Self::Fingertip { rx_mm, ry_mm } => {
                let q = (x / rx_mm).powi(2) + (y / ry_mm).powi(2);
                // A soft pad flattens against the gel: flat middle, walls rising steeply towards
                // the rim (quartic in the elliptic radius), 2.5 mm high at the rim.
                if q < 1.5 { 2.5 * q * q } else { f64::INFINITY }
            }
        }
    }
}

/// A cube's corner pointing down: three faces at equal angles, the tip rounded a little.
fn cube_corner_height(x: f64, y: f64) -> f64 {
    let s = std::f64::consts::SQRT_2;
    let mut h: f64 = 0.0;
    for k in 0..3 {
        let a = std::f64::consts::TAU * f64::from(k) / 3.0 + std::f64::consts::FRAC_PI_2;
        h = h.max(s * (x * a.cos() + y * a.sin()));
    }
    let t = 0.15;
    (h * h + t * t).sqrt() - t
}

/// The outline of a five-pointed star of outer radius `radius_mm`, a point up.
fn star_polygon(radius_mm: f64) -> Vec<[f64; 2]> {
    (0..10)
        .map(|k| {
            let a = -std::f64::consts::FRAC_PI_2 + std::f64::consts::PI * f64::from(k) / 5.0;
            let r = if k % 2 == 0 { radius_mm } else { 0.45 * radius_mm };
            [r * a.cos(), r * a.sin()]
        })
        .collect()
}

/// A stamp with raised letters `text` of `height_mm`: strokes 0.2 letter-heights wide
/// (resolved by the physics grid); letters stand 0.5 mm proud of the stamp, whose edge is well
/// outside the letters.
fn text_height(text: &str, height_mm: f64, x: f64, y: f64) -> f64 {
    let n = text.chars().count().max(1) as f64;
    let advance = 0.85;
    let x0 = -0.5 * (n * advance - 0.25);
    let (u, v) = (x / height_mm - x0, y / height_mm + 0.5);
    let mut d = f64::INFINITY;
    for (k, c) in text.chars().enumerate() {
        let ox = k as f64 * advance;
        for s in glyph(c) {
            d = d.min(sd_segment(u, v, [s[0] + ox, s[1]], [s[2] + ox, s[3]]));
        }
    }
    let stroke = (d - 0.1) * height_mm;
    let stamp = fillet((x.abs() - 0.5 * (n * advance + 0.6) * height_mm).max(y.abs() - 0.8 * height_mm));
    fillet(stroke).min(0.5) + stamp
}

/// A sphere of radius `r` with Gaussian bumps (centre x, centre y, radius, height), lifted so
/// that the tallest bump's top is the lowest point.
fn bumpy_height(r: f64, bumps: &[[f64; 4]], x: f64, y: f64) -> f64 {
    let r2 = x * x + y * y;
    if r2 >= r * r {
        return f64::INFINITY;
    }
    let mut h = r - (r * r - r2).sqrt();
    let peak: f64 = bumps.iter().map(|b| b[3]).fold(0.0, f64::max);
    for b in bumps {
        let d2 = (x - b[0]).powi(2) + (y - b[1]).powi(2);
        h -= b[3] * (-d2 / (2.0 * b[2] * b[2])).exp();
    }
    (h + peak).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn every_shape_touches_at_its_centre_region_and_rises_outside() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for name in SHAPES {
            let ind = Indenter::random(name, 1.0, &mut rng).unwrap();
            assert_eq!(ind.name(), name);
            let mut min = f64::INFINITY;
            for i in -40..=40 {
                for j in -40..=40 {
                    min = min.min(ind.height(f64::from(i) * 0.1, f64::from(j) * 0.1));
                }
            }
            assert!(min < 0.4, "{name}: lowest point {min}");
            assert!(ind.height(15.0, 15.0) > 1.0, "{name}: far corner should be high");
        }
        assert!(Indenter::random("teapot", 1.0, &mut rng).is_none());
    }
}
