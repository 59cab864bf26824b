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

/// A pattern over the image or the gel that is not a marker (wider domain randomisation).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Texture {
    /// Stripes from the camera's readout or the LED driver: scan lines (period of a few px) or
    /// wider banding. Multiplies every pixel, markers included, by `1 + gain * profile`, the profile
    /// a sine across the stripes sharpened towards a square wave by `sharpness` (>= 1).
    Bands {
        /// Stripe period, px (full resolution).
        period_px: f32,
        /// Direction across the stripes, radians (0: vertical stripes; pi/2: horizontal lines).
        angle: f32,
        /// Phase, radians.
        phase: f32,
        /// Relative gain per channel.
        gain: [f32; 3],
        /// 1 = sine, larger = squarer.
        sharpness: f32,
    },
    /// Moire: the beat of two fine gratings of close period and direction (a screen, a fabric or
    /// the sensor's pixel grid against a printed pattern). Multiplicative, like [`Texture::Bands`].
    Moire {
        /// Period of the first grating, px.
        period_px: f32,
        /// Direction of the first grating, radians.
        angle: f32,
        /// Relative period difference of the second grating.
        detune: f32,
        /// Direction difference of the second grating, radians.
        twist: f32,
        /// Relative gain of the beat fringes.
        gain: f32,
    },
    /// A fingerprint left on the gel or the lens: wavy concentric ridges around `at`, fading out
    /// at `radius_px`. Added to the background, in grey levels.
    Fingerprint {
        /// Centre, as a fraction of the image width and height.
        at: [f32; 2],
        /// Ridge period, px.
        period_px: f32,
        /// Radius of the print, px.
        radius_px: f32,
        /// Ridge contrast, grey levels.
        amplitude: f32,
    },
}

/// Newton rings: interference in the thin air film between the gel and a smooth object, seen as
/// rings following the indentation's depth contours where the gel is pressed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NewtonRings {
    /// Indentation depth between two bright rings, mm.
    pub period_mm: f32,
    /// Ring contrast per channel, grey levels.
    pub amplitude: [f32; 3],
}

/// A specular glint on the markers: a small bright spot off each dot's centre (glossy ink or
/// raised pins lit by the LEDs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Glint {
    /// Offset of the spot from the dot centre, in dot radii (x, y).
    pub offset: [f32; 2],
    /// Spot radius, in dot radii.
    pub size: f32,
    /// Spot opacity.
    pub alpha: f32,
    /// Share of the markers that carry a glint (chosen per marker, fixed for the recording).
    pub share: f32,
}

/// What the cameras see outside a membrane (sensors whose gel does not fill the view).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Housing {
    /// Housing colour.
    pub color: [f32; 3],
    /// Colour of the rim around the membrane.
    pub rim_color: [f32; 3],
    /// Rim width, mm.
    pub rim_mm: f32,
    /// Round things on the housing (screws, holes, LEDs seen sideways): x, y, radius (mm) and
    /// grey level. Dot-like on purpose: they are not markers.
    pub clutter: Vec<[f32; 4]>,
    /// LED glints just outside the rim: x, y, radius (mm) and peak brightness added.
    pub glints: Vec<[f32; 4]>,
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
    /// Patterns over the image or the gel (none in the narrower randomisations).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub textures: Vec<Texture>,
    /// Newton rings in the pressed gel.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub newton_rings: Option<NewtonRings>,
    /// Glints on the markers.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub glint: Option<Glint>,
    /// The housing around a membrane (used when the sensor has one; a plain dark housing without).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub housing: Option<Housing>,
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
            textures: Vec::new(),
            newton_rings: None,
            glint: None,
            housing: None,
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
            textures: Vec::new(),
            newton_rings: None,
            glint: None,
            housing: None,
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
            textures: Vec::new(),
            newton_rings: None,
            glint: None,
            housing: None,
        }
    }
}

/// Relative luminance (Rec. 601 weights), 0..255.
pub fn luminance(c: [f32; 3]) -> f32 {
    0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2]
}

/// RGB (0..255) of hue `h` (radians), saturation `s` and value `v` (0..255).
fn hsv(h: f32, s: f32, v: f32) -> [f32; 3] {
    let hue = [0.0f32, 2.0, 4.0].map(|k| {
        let x = (h / std::f32::consts::FRAC_PI_3 + k).rem_euclid(6.0);
        let ramp = (x - 3.0).abs() - 1.0;
        ramp.clamp(0.0, 1.0)
    });
    hue.map(|c| v * (1.0 - s + s * c))
}

impl Appearance {
    /// A random look of the widened domain (`--randomization wide`): [`Appearance::random`] or
    /// [`Appearance::random_gelsight_like`], then one marker family in four differs from the gel
    /// mostly in hue (e.g. yellow-green dots on a darker blue-green gel), and image textures
    /// (scan lines, banding, moire, fingerprints), Newton rings and marker glints are added at
    /// random.
    pub fn random_wide(rng: &mut impl Rng) -> Self {
        let mut app = if rng.random_bool(0.25) {
            Self::random_gelsight_like(rng)
        } else {
            Self::random(rng)
        };
        if rng.random_bool(0.25) {
            app.recolour_by_hue(rng);
        }
        let n_textures = [0usize, 0, 1, 1, 1, 2][rng.random_range(0..6)];
        app.textures = (0..n_textures).map(|_| random_texture(rng)).collect();
        if rng.random_bool(0.3) {
            app.newton_rings = Some(NewtonRings {
                period_mm: rng.random_range(0.02..0.12),
                amplitude: [0; 3].map(|_| rng.random_range(8.0..40.0)),
            });
        }
        if rng.random_bool(0.3) {
            let a: f32 = rng.random_range(0.0..std::f32::consts::TAU);
            let d: f32 = rng.random_range(0.2..0.55);
            app.glint = Some(Glint {
                offset: [d * a.cos(), d * a.sin()],
                size: rng.random_range(0.15..0.4),
                alpha: rng.random_range(0.4..0.95),
                share: rng.random_range(0.2..1.0),
            });
        }
        app
    }

    /// Makes the markers differ from the gel mostly in colour: a saturated gel colour and marker
    /// colour of another hue whose luminance is 0.85 to 1.6 times the gel's.
    fn recolour_by_hue(&mut self, rng: &mut impl Rng) {
        let gel_hue: f32 = rng.random_range(0.0..std::f32::consts::TAU);
        let gel = hsv(
            gel_hue,
            rng.random_range(0.4..0.85),
            rng.random_range(70.0..170.0),
        );
        let turn = rng.random_range(1.0..2.6) * if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        let dot = hsv(gel_hue + turn, rng.random_range(0.5..0.95), 200.0);
        let target = luminance(gel) * rng.random_range(0.85..1.6);
        let k = target / luminance(dot).max(1.0);
        self.background = gel;
        self.marker_color = dot.map(|c| (c * k).clamp(0.0, 255.0));
        self.marker_alpha = rng.random_range(0.75..1.0);
    }
}

fn random_texture(rng: &mut impl Rng) -> Texture {
    match rng.random_range(0..4) {
        // Scan lines: fine, horizontal.
        0 => Texture::Bands {
            period_px: rng.random_range(2.5..8.0),
            angle: std::f32::consts::FRAC_PI_2 + rng.random_range(-0.02..0.02),
            phase: rng.random_range(0.0..std::f32::consts::TAU),
            gain: [rng.random_range(0.04..0.22); 3],
            sharpness: rng.random_range(1.0..4.0),
        },
        // Banding: wider stripes, tinted, any direction but mostly horizontal.
        1 => Texture::Bands {
            period_px: rng.random_range(8.0..60.0),
            angle: if rng.random_bool(0.7) {
                std::f32::consts::FRAC_PI_2
            } else {
                rng.random_range(0.0..std::f32::consts::PI)
            },
            phase: rng.random_range(0.0..std::f32::consts::TAU),
            gain: [0; 3].map(|_| rng.random_range(0.03..0.25)),
            sharpness: rng.random_range(1.0..6.0),
        },
        2 => Texture::Moire {
            period_px: rng.random_range(2.2..5.0),
            angle: rng.random_range(0.0..std::f32::consts::PI),
            detune: rng.random_range(0.03..0.2),
            twist: rng.random_range(-0.08..0.08),
            gain: rng.random_range(0.04..0.2),
        },
        _ => Texture::Fingerprint {
            at: [rng.random_range(0.1..0.9), rng.random_range(0.1..0.9)],
            period_px: rng.random_range(3.0..9.0),
            radius_px: rng.random_range(40.0..200.0),
            amplitude: rng.random_range(6.0..30.0),
        },
    }
}

/// A random housing around `membrane`: colour, rim, round clutter and LED glints just outside
/// the rim (all on the housing, none inside the membrane).
pub fn random_housing(rng: &mut impl Rng, membrane: &gelstereo_sensor::Membrane, pitch_mm: f64) -> Housing {
    let bright = rng.random_bool(0.5);
    let v = if bright {
        rng.random_range(150.0..245.0)
    } else {
        rng.random_range(10.0..80.0)
    };
    let color = [0; 3].map(|_| v * rng.random_range(0.85..1.15f32));
    let rim_v = rng.random_range(20.0..240.0f32);
    let rim_color = [0; 3].map(|_| rim_v * rng.random_range(0.8..1.2f32));
    let rim_mm = (pitch_mm * rng.random_range(0.2..1.2)) as f32;
    // Points outside the outline: walk out along a random direction until clear of the rim.
    let outside = |rng: &mut dyn rand::RngCore, clearance: f64| -> Option<[f32; 2]> {
        let a = rng.next_u32() as f64 / f64::from(u32::MAX) * std::f64::consts::TAU;
        let (dx, dy) = (a.cos(), a.sin());
        let mut r = 0.0;
        while r < 200.0 {
            if membrane.signed_distance_mm(r * dx, r * dy) > clearance {
                return Some([(r * dx) as f32, (r * dy) as f32]);
            }
            r += 0.25 * pitch_mm;
        }
        None
    };
    let mut clutter = Vec::new();
    for _ in 0..rng.random_range(0..8) {
        let radius = pitch_mm * rng.random_range(0.15..0.6);
        let extra = pitch_mm * rng.random_range(0.5..4.0);
        if let Some(p) = outside(rng, f64::from(rim_mm) + radius + extra) {
            let g = if rng.random_bool(0.5) {
                rng.random_range(0.0..60.0)
            } else {
                rng.random_range(180.0..255.0)
            };
            clutter.push([p[0], p[1], radius as f32, g]);
        }
    }
    let mut glints = Vec::new();
    for _ in 0..rng.random_range(0..6) {
        let radius = pitch_mm * rng.random_range(0.2..1.0);
        if let Some(p) = outside(rng, f64::from(rim_mm) + 0.5 * radius) {
            glints.push([p[0], p[1], radius as f32, rng.random_range(60.0..220.0)]);
        }
    }
    Housing {
        color,
        rim_color,
        rim_mm,
        clutter,
        glints,
    }
}
