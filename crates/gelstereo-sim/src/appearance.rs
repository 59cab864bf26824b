//! How a sensor looks: gel and marker colours, LED lighting, optics and camera noise. One
//! [`Appearance`] per recording; [`Appearance::random`] is the domain randomisation.

use rand::Rng;
use serde::{Deserialize, Serialize};

/// A speck of dust or a scratch on the gel or the lens: not a marker.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Dust {
    /// Centre, as a fraction of the image width and height.
    pub at: [f64; 2],
    /// Radius, px (of a 640-wide image; scaled with the image).
    pub radius_px: f64,
    /// Elongation (1 = round; a scratch is long and thin).
    pub elongation: f64,
    /// Direction of the long axis, radians.
    pub angle: f64,
    /// RGB colour.
    pub color: [f32; 3],
    /// Opacity.
    pub alpha: f32,
}

/// Everything about the look of one recording. Colours are RGB in 0..255.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Appearance {
    /// Gel colour under flat illumination at the image centre.
    pub background: [f32; 3],
    /// Colour change across the gel from left to right edge (LED gradient).
    pub gradient_x: [f32; 3],
    /// Colour change across the gel from top to bottom edge.
    pub gradient_y: [f32; 3],
    /// Colour change from the centre to the corners (radial LED falloff).
    pub gradient_radial: [f32; 3],
    /// Per channel, direction (x, y) of the LED that lights it, in the sensor plane.
    pub light_dirs: [[f32; 2]; 3],
    /// Shading gain: colour change per unit surface slope.
    pub light_gain: f32,
    /// Marker colour.
    pub marker_color: [f32; 3],
    /// Marker opacity at rest (contrast).
    pub marker_alpha: f32,
    /// Multiplies the sensor's dot diameter.
    pub dot_scale: f64,
    /// Width of the marker's soft edge, px.
    pub edge_softness_px: f32,
    /// How much markers fade where the gel touches the object (0 none, 1 vanish).
    pub contact_fade: f32,
    /// Colour the contact region tends to.
    pub contact_tint: [f32; 3],
    /// Strength of that tint.
    pub contact_tint_strength: f32,
    /// Defocus blur, Gaussian sigma in px.
    pub blur_px: f64,
    /// Sensor noise, standard deviation in grey levels.
    pub noise: f32,
    /// Vignetting: relative darkening at the image corners.
    pub vignette: f32,
    /// JPEG quality when the frames go through a JPEG round trip (artefacts), else none.
    pub jpeg_quality: Option<i32>,
    /// Dust specks and scratches.
    pub dust: Vec<Dust>,
    /// Exposure time as a fraction of the frame interval: moving markers smear over it.
    pub motion_blur: f64,
    /// Contrast of skin ridges (fingertip contacts), grey levels.
    pub ridge_gain: f32,
}

fn rgb(r: f32, g: f32, b: f32) -> [f32; 3] {
    [r, g, b]
}

impl Appearance {
    /// The reference sensor's look: a light gel lit by warm and cool LEDs from the sides, black
    /// printed dots, mild blur and noise.
    pub fn reference() -> Self {
        Self {
            background: rgb(196.0, 192.0, 186.0),
            gradient_x: rgb(18.0, -4.0, -16.0),
            gradient_y: rgb(-8.0, 6.0, 14.0),
            gradient_radial: rgb(-6.0, -8.0, -4.0),
            light_dirs: [[0.9, 0.3], [-0.6, 0.7], [-0.3, -0.95]],
            light_gain: 140.0,
            marker_color: rgb(28.0, 27.0, 32.0),
            marker_alpha: 0.92,
            dot_scale: 1.0,
            edge_softness_px: 1.2,
            contact_fade: 0.45,
            contact_tint: rgb(232.0, 230.0, 226.0),
            contact_tint_strength: 0.25,
            blur_px: 0.7,
            noise: 1.5,
            vignette: 0.22,
            jpeg_quality: None,
            motion_blur: 0.3,
            ridge_gain: 8.0,
            dust: vec![
                Dust {
                    at: [0.18, 0.72],
                    radius_px: 2.0,
                    elongation: 1.0,
                    angle: 0.0,
                    color: rgb(60.0, 55.0, 50.0),
                    alpha: 0.5,
                },
                Dust {
                    at: [0.81, 0.2],
                    radius_px: 1.2,
                    elongation: 6.0,
                    angle: 0.7,
                    color: rgb(235.0, 235.0, 235.0),
                    alpha: 0.35,
                },
            ],
        }
    }

    /// A random look (domain randomisation): colours, polarity (dark-on-light or light-on-dark),
    /// lighting, marker size and contrast, blur, noise, vignetting, JPEG and dust.
    /// One in five looks is [`Appearance::random_gelsight_like`].
    pub fn random(rng: &mut impl Rng) -> Self {
        if rng.random_bool(0.2) {
            return Self::random_gelsight_like(rng);
        }
        let mut u = |lo: f32, hi: f32| rng.random_range(lo..hi);
        let dark_markers = u(0.0, 1.0) < 0.75;
        // A colour of brightness `v` with a random tint.
        let tinted = |v: f32, sat: f32, u: &mut dyn FnMut(f32, f32) -> f32| {
            let t = [u(-1.0, 1.0), u(-1.0, 1.0), u(-1.0, 1.0)];
            [0, 1, 2].map(|k| (v * (1.0 + sat * t[k])).clamp(0.0, 255.0))
        };
        let (background, marker_color) = if dark_markers {
            let bg_v = u(70.0, 235.0);
            let bg = tinted(bg_v, u(0.0, 0.45), &mut u);
            let m_v = u(0.0, 0.45) * bg_v;
            (bg, tinted(m_v, u(0.0, 0.4), &mut u))
        } else {
            let bg_v = u(15.0, 95.0);
            let bg = tinted(bg_v, u(0.0, 0.5), &mut u);
            let m_v = u(150.0, 255.0);
            (bg, tinted(m_v, u(0.0, 0.3), &mut u))
        };
        // LED colour gradients: mostly mild, sometimes as strong as a GelSight's.
        let amp = u(0.0, 1.0).powi(2) * 90.0;
        let gradient_x = [0; 3].map(|_| amp * u(-1.0, 1.0));
        let gradient_y = [0; 3].map(|_| amp * u(-1.0, 1.0));
        let gradient_radial = [0; 3].map(|_| amp * u(-1.0, 1.0));
        let phase = u(0.0, std::f32::consts::TAU);
        let light_dirs = [0, 1, 2].map(|k| {
            let a = phase + k as f32 * std::f32::consts::TAU / 3.0 + u(-0.5, 0.5);
            [a.cos(), a.sin()]
        });
        let n_dust = (u(0.0, 1.0).powi(2) * 12.0) as usize;
        let dust = (0..n_dust)
            .map(|_| {
                let bright = u(0.0, 1.0) < 0.4;
                let v = if bright { u(180.0, 255.0) } else { u(0.0, 90.0) };
                Dust {
                    at: [f64::from(u(0.0, 1.0)), f64::from(u(0.0, 1.0))],
                    radius_px: f64::from(u(0.6, 3.5)),
                    elongation: if u(0.0, 1.0) < 0.25 {
                        f64::from(u(3.0, 12.0))
                    } else {
                        f64::from(u(1.0, 1.6))
                    },
                    angle: f64::from(u(0.0, 3.2)),
                    color: [v, v, v],
                    alpha: u(0.2, 0.8),
                }
            })
            .collect();
        let contact_tint = if u(0.0, 1.0) < 0.5 {
            tinted(u(180.0, 255.0), 0.2, &mut u)
        } else {
            tinted(u(20.0, 120.0), 0.3, &mut u)
        };
        Self {
            background,
            gradient_x,
            gradient_y,
            gradient_radial,
            light_dirs,
            light_gain: u(20.0, 220.0),
            marker_color,
            marker_alpha: u(0.45, 1.0),
            dot_scale: f64::from(u(0.7, 1.35)),
            edge_softness_px: u(0.8, 2.2),
            contact_fade: u(0.0, 0.8),
            contact_tint,
            contact_tint_strength: u(0.0, 0.45),
            blur_px: f64::from(u(0.3, 2.0)),
            noise: u(0.0, 6.0),
            vignette: u(0.0, 0.85),
            jpeg_quality: if u(0.0, 1.0) < 0.35 {
                Some(u(35.0, 95.0) as i32)
            } else {
                None
            },
            dust,
            motion_blur: if u(0.0, 1.0) < 0.5 {
                f64::from(u(0.0, 1.0))
            } else {
                0.0
            },
            ridge_gain: u(0.0, 18.0),
        }
    }

    /// A random look in the family of GelSight-type sensors: a darker gel lit by coloured LEDs
    /// (blue-violet centre, teal and green towards the rim), strong vignetting and colour shading,
    /// black dots, video-compression artefacts.
    pub fn random_gelsight_like(rng: &mut impl Rng) -> Self {
        let mut u = |lo: f32, hi: f32| rng.random_range(lo..hi);
        let background = rgb(u(90.0, 170.0), u(95.0, 145.0), u(130.0, 200.0));
        let gradient_y = rgb(u(80.0, 240.0), u(-20.0, 80.0), u(20.0, 120.0));
        let gradient_x = rgb(u(-40.0, 40.0), u(-30.0, 30.0), u(-40.0, 40.0));
        let gradient_radial = rgb(u(-120.0, -30.0), u(-60.0, 10.0), u(-100.0, -20.0));
        let phase = u(0.0, std::f32::consts::TAU);
        let light_dirs = [0, 1, 2].map(|k| {
            let a = phase + k as f32 * std::f32::consts::TAU / 3.0 + u(-0.3, 0.3);
            [a.cos(), a.sin()]
        });
        let m = u(0.0, 35.0);
        let n_dust = (u(0.0, 1.0) * 6.0) as usize;
        let dust = (0..n_dust)
            .map(|_| Dust {
                at: [f64::from(u(0.0, 1.0)), f64::from(u(0.0, 1.0))],
                radius_px: f64::from(u(0.6, 2.5)),
                elongation: f64::from(u(1.0, 1.5)),
                angle: f64::from(u(0.0, 3.2)),
                color: [u(20.0, 80.0); 3],
                alpha: u(0.2, 0.6),
            })
            .collect();
        Self {
            background,
            gradient_x,
            gradient_y,
            gradient_radial,
            light_dirs,
            light_gain: u(120.0, 320.0),
            marker_color: rgb(m, m * u(0.8, 1.2), m * u(0.8, 1.3)),
            marker_alpha: u(0.8, 1.0),
            dot_scale: f64::from(u(0.8, 1.2)),
            edge_softness_px: u(1.0, 2.5),
            contact_fade: u(0.0, 0.4),
            contact_tint: rgb(u(150.0, 255.0), u(120.0, 220.0), u(170.0, 255.0)),
            contact_tint_strength: u(0.0, 0.35),
            blur_px: f64::from(u(0.6, 1.8)),
            noise: u(0.5, 4.0),
            vignette: u(0.45, 0.9),
            jpeg_quality: if u(0.0, 1.0) < 0.7 {
                Some(u(30.0, 85.0) as i32)
            } else {
                None
            },
            dust,
            motion_blur: if u(0.0, 1.0) < 0.6 {
                f64::from(u(0.2, 1.0))
            } else {
                0.0
            },
            ridge_gain: u(3.0, 18.0),
        }
    }
}
