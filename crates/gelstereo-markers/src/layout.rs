//! Where an image lies in Marknet's input ([`InputLayout`]) and how the layout is chosen: the fits of
//! [`InputFit`], the "auto" fit of a dynamic-input model ([`fit_layout`], `docs/model-contract.md`)
//! with its probes and relayout rules, and the decoding geometry of an image run under a layout.
//! Shared by the localizer, its lattice window, its closer look and the resize kernels.

use std::path::PathBuf;

use gelstereo_core::{Detection, ImageSize};

use crate::contract::AutoFit;
use crate::postprocess::{DecodeGeometry, decode};
use crate::{Error, Result};

/// How an image is brought to the network's input size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum InputFit {
    /// The model's own fit: for a dynamic-input model (`gelstereo-marknet/2`) the "auto" layout of
    /// [`fit_layout`] (isotropic, marker pitch brought into the trained range, a margin of the median
    /// colour), with the pitch measured on a first pass and remembered per image size; for a
    /// fixed-input model the contract's [`Stretch`](Self::Stretch).
    #[default]
    Auto,
    /// The whole image resized to the nominal input size (anisotropically if the aspect ratios
    /// differ): the first contract's preprocessing.
    Stretch,
    /// Isotropic: scaled by `min(input_width / W, input_height / H, 1)` (never enlarged), centred in
    /// the nominal input, the rest filled with the image's median colour.
    Pad,
}

impl std::str::FromStr for InputFit {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "auto" => Ok(Self::Auto),
            "stretch" => Ok(Self::Stretch),
            "pad" => Ok(Self::Pad),
            _ => Err(Error::Config {
                path: PathBuf::from("(command line)"),
                field: "fit".into(),
                expected: "auto, stretch or pad".into(),
                found: s.to_owned(),
            }),
        }
    }
}

/// How a localizer fits images to its model's input: the [`InputFit`] chosen, and the model's nominal
/// input size and "auto" fit rules (its contract's).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModelFit {
    /// The fit chosen.
    pub fit: InputFit,
    /// The model's nominal input width, px.
    pub input_width: u32,
    /// The model's nominal input height, px.
    pub input_height: u32,
    /// The model's "auto" fit rules (`None`: a fixed-input model).
    pub auto_fit: Option<AutoFit>,
}

impl ModelFit {
    /// The "auto" fit's rules where it applies (an [`InputFit::Auto`] fit of a dynamic-input model).
    pub fn auto(&self) -> Option<&AutoFit> {
        match self.fit {
            InputFit::Auto => self.auto_fit.as_ref(),
            InputFit::Stretch | InputFit::Pad => None,
        }
    }

    /// The layout of an image of `size` given its marker pitch (used by the "auto" fit only).
    pub fn layout(&self, size: ImageSize, pitch_px: Option<f64>) -> InputLayout {
        let (iw, ih) = (self.input_width, self.input_height);
        if let Some(fit) = self.auto() {
            return fit_layout(size, pitch_px, iw, ih, fit);
        }
        match self.fit {
            InputFit::Pad => {
                let (w, h) = (f64::from(size.width), f64::from(size.height));
                let scale = (f64::from(iw) / w).min(f64::from(ih) / h).min(1.0);
                let nw = ((w * scale).round() as u32).clamp(1, iw);
                let nh = ((h * scale).round() as u32).clamp(1, ih);
                InputLayout {
                    input_width: iw,
                    input_height: ih,
                    scaled_width: nw,
                    scaled_height: nh,
                    offset_x: (iw - nw) / 2,
                    offset_y: (ih - nh) / 2,
                }
            }
            InputFit::Auto | InputFit::Stretch => InputLayout::stretch(iw, ih),
        }
    }

    /// The nominal input whose aspect ratio an image must keep within bounds: a whole-image
    /// stretch's (the "auto" and "pad" layouts keep the image's own).
    pub fn stretch_to(&self) -> Option<(u32, u32)> {
        let stretch =
            self.fit == InputFit::Stretch || (self.fit == InputFit::Auto && self.auto_fit.is_none());
        stretch.then_some((self.input_width, self.input_height))
    }
}

/// Largest side of a network input the "auto" fit builds, px (bounds memory and time on huge images).
pub const MAX_INPUT_SIDE_PX: u32 = 2048;

/// A second pass is run when the measured pitch asks for a scale more than this (relative) away
/// from the one used (`RELAYOUT_SCALE_CHANGE` in the trainer).
pub const RELAYOUT_SCALE_CHANGE: f64 = 0.1;

/// Passes at the layout of a measured pitch, at most, with the lattice check on (one without it;
/// `MAX_RELAYOUTS` in the trainer). A lattice the network resolves only in part at one scale shows a
/// pitch that overstates the true one (its few finds lie apart), so one step leaves it still too
/// small; each pass brings the pitch closer (a fine sensor measured in steps:
/// `docs/experiments/localization-input-and-speed.md`).
pub const MAX_RELAYOUTS: usize = 3;

/// Confident candidates (c > `conf_keep`) needed before a measured pitch may change the layout
/// (`MIN_PITCH_SUPPORT` in the trainer).
pub const MIN_PITCH_SUPPORT: usize = 8;

/// Scale of the probe relative to the nominal fit (`PROBE_SCALE` in the trainer). A first pass without
/// a known pitch is run once more at this scale; the probe measures the pitch instead when it finds at
/// least [`MIN_PITCH_SUPPORT`] and [`PROBE_MIN_GAIN`] times as many confident candidates, covering at
/// least [`PROBE_MIN_COVER`] of the area the first pass's cover. A sensor whose marker pitch falls below
/// the network's range at the nominal fit (a 10 px pitch on an 800 x 600 image, 5 px at 416 x 320) shows
/// only a scattered few markers there, whose nearest-neighbour distances overstate the pitch, so that
/// pass alone never asks for the larger scale. A stream pays the probe once per image size (the pitch
/// is remembered).
pub const PROBE_SCALE: f64 = 2.0;

/// Scale of the fine probe relative to the nominal fit (`FINE_PROBE_SCALE` in the trainer): when
/// neither the first pass nor the probe finds a lattice, the image is probed once more at this scale,
/// kept under the probe's rule. A fine lattice on a large image (a 9 px pitch at 1280 x 720 is 2.9 px
/// at the nominal fit and 5.9 px in the probe, under the 8 px the lattice check needs) shows only
/// there. Images with a lattice never pay for it; a stream pays it only until a pitch is remembered.
pub const FINE_PROBE_SCALE: f64 = 4.0;

/// Scale of the coarse probe relative to the nominal fit (`COARSE_PROBE_SCALE` in the trainer): where
/// no pass so far found a lattice, the image is probed at this scale too, kept under the probe's rule.
/// A coarse sensor (a 50 px pitch on a 320 x 240 image is 65 px at the nominal fit, beyond the
/// network's range, where it finds nothing or several finds per dot) shows its lattice only there.
pub const COARSE_PROBE_SCALE: f64 = 0.25;

/// How many times the first pass's confident candidates the probe must find (`PROBE_MIN_GAIN` in the
/// trainer): a sensor the nominal fit serves keeps its first pass (a few more finds at another scale
/// would only move the layout a little), one it fails gains several times over.
pub const PROBE_MIN_GAIN: f64 = 2.0;

/// Share of the first pass's covered area (confident candidates x pitch^2) the probe must cover
/// (`PROBE_MIN_COVER` in the trainer).
pub const PROBE_MIN_COVER: f64 = 0.5;

/// Where an image lies in the network input: resized to `scaled_width x scaled_height` and placed at
/// (`offset_x`, `offset_y`) in an input of `input_width x input_height`, the rest filled with its median colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct InputLayout {
    /// Network input width, px.
    pub input_width: u32,
    /// Network input height, px.
    pub input_height: u32,
    /// Width of the resized image inside the input, px.
    pub scaled_width: u32,
    /// Height of the resized image inside the input, px.
    pub scaled_height: u32,
    /// Input columns left of the image.
    pub offset_x: u32,
    /// Input rows above the image.
    pub offset_y: u32,
}

impl InputLayout {
    /// The whole image resized to `width x height` (no padding): the first contract's stretch.
    pub fn stretch(width: u32, height: u32) -> Self {
        Self {
            input_width: width,
            input_height: height,
            scaled_width: width,
            scaled_height: height,
            offset_x: 0,
            offset_y: 0,
        }
    }

    /// The whole input is the image (no padding).
    fn fills_input(&self) -> bool {
        self.scaled_width == self.input_width && self.scaled_height == self.input_height
    }

    /// Whether an image under `self` should be run again under `wanted` (scale along x or y off by
    /// more than [`RELAYOUT_SCALE_CHANGE`]).
    pub fn needs_relayout(&self, wanted: &InputLayout) -> bool {
        let off = |a: u32, b: u32| (f64::from(a) / f64::from(b.max(1)) - 1.0).abs() > RELAYOUT_SCALE_CHANGE;
        off(wanted.scaled_width, self.scaled_width) || off(wanted.scaled_height, self.scaled_height)
    }
}

/// The "auto" layout (`docs/model-contract.md`) of an image of `size` whose marker pitch is `pitch_px`
/// (original px; `None`: unknown, then no margin and no pitch check) for a model of nominal input
/// `nominal_width x nominal_height`. Mirrors `fit_layout` of the trainer (`postprocess.py`).
pub fn fit_layout(
    size: ImageSize,
    pitch_px: Option<f64>,
    nominal_width: u32,
    nominal_height: u32,
    fit: &AutoFit,
) -> InputLayout {
    let p = pitch_px.filter(|p| p.is_finite() && *p > 0.0).unwrap_or(0.0);
    let (w, h) = (f64::from(size.width), f64::from(size.height));
    let in_range = |v: f64| (fit.pitch_min_px..=fit.pitch_max_px).contains(&v);
    if fit.prefer_stretch
        && (p == 0.0
            || (in_range(p * f64::from(nominal_width) / w) && in_range(p * f64::from(nominal_height) / h)))
    {
        return InputLayout::stretch(nominal_width, nominal_height);
    }
    let mut s = (f64::from(nominal_width) / (w + p)).min(f64::from(nominal_height) / (h + p));
    if p > 0.0 && !(fit.pitch_min_px..=fit.pitch_max_px).contains(&(p * s)) {
        s = fit.pitch_target_px / p;
    }
    layout_at_scale(w, h, p, s, fit.multiple)
}

/// The layout of a `w x h` image at scale `s` with a margin of `p` px (capped so that no input side
/// exceeds [`MAX_INPUT_SIDE_PX`]), its input sides rounded up to multiples of `multiple`.
pub(crate) fn layout_at_scale(w: f64, h: f64, p: f64, s: f64, multiple: u32) -> InputLayout {
    let max_side = f64::from(MAX_INPUT_SIDE_PX);
    let s = s.min(max_side / (w + p)).min(max_side / (h + p));
    let m = f64::from(multiple.max(1));
    let ceil_to = |v: f64| (((v / m - 1e-9).ceil().max(1.0)) * m) as u32;
    let (input_width, input_height) = (ceil_to(s * (w + p)), ceil_to(s * (h + p)));
    let scaled_width = ((s * w).round() as u32).clamp(1, input_width);
    let scaled_height = ((s * h).round() as u32).clamp(1, input_height);
    InputLayout {
        input_width,
        input_height,
        scaled_width,
        scaled_height,
        offset_x: (input_width - scaled_width) / 2,
        offset_y: (input_height - scaled_height) / 2,
    }
}

/// The probe of the "auto" fit: the isotropic layout of an image of `size` at [`PROBE_SCALE`] times the
/// nominal fit's scale, no margin (sides capped at [`MAX_INPUT_SIDE_PX`]).
pub fn probe_layout(size: ImageSize, nominal_width: u32, nominal_height: u32, fit: &AutoFit) -> InputLayout {
    probe_layout_at(size, nominal_width, nominal_height, fit, PROBE_SCALE)
}

/// [`probe_layout`] at `scale` times the nominal fit's scale ([`FINE_PROBE_SCALE`] for the fine probe,
/// [`COARSE_PROBE_SCALE`] for the coarse one).
pub(crate) fn probe_layout_at(
    size: ImageSize,
    nominal_width: u32,
    nominal_height: u32,
    fit: &AutoFit,
    scale: f64,
) -> InputLayout {
    let (w, h) = (f64::from(size.width), f64::from(size.height));
    let nominal = (f64::from(nominal_width) / w).min(f64::from(nominal_height) / h);
    layout_at_scale(w, h, 0.0, scale * nominal, fit.multiple)
}

/// Input px per original px of an image of `size` under `layout` (geometric mean of the two axes).
pub fn input_per_px(size: ImageSize, layout: &InputLayout) -> f64 {
    let sx = f64::from(layout.scaled_width) / f64::from(size.width.max(1));
    let sy = f64::from(layout.scaled_height) / f64::from(size.height.max(1));
    (sx * sy).sqrt()
}

/// The decoding geometry of an image of `size` run under `layout` by a network of output `stride`
/// with `candidates` slots per cell.
pub fn layout_geometry(
    size: ImageSize,
    layout: &InputLayout,
    stride: u32,
    candidates: u32,
) -> DecodeGeometry {
    DecodeGeometry {
        grid_y: (layout.input_height / stride.max(1)) as usize,
        grid_x: (layout.input_width / stride.max(1)) as usize,
        candidates: candidates as usize,
        stride: f64::from(stride),
        scale_x: f64::from(size.width) / f64::from(layout.scaled_width.max(1)),
        scale_y: f64::from(size.height) / f64::from(layout.scaled_height.max(1)),
        offset_x: f64::from(layout.offset_x),
        offset_y: f64::from(layout.offset_y),
    }
}

/// [`decode`] of one image of `size` run under `layout`, without the candidates in the padding
/// around the image (a marker whose centre lies outside the image is not reported).
pub fn decode_in_layout(
    raw: &[f32],
    geometry: &DecodeGeometry,
    layout: &InputLayout,
    size: ImageSize,
    min_confidence: f32,
) -> Vec<Detection> {
    let mut dets = decode(raw, geometry, min_confidence);
    if !layout.fills_input() {
        let (w, h) = (f64::from(size.width) - 0.5, f64::from(size.height) - 0.5);
        dets.retain(|d| (-0.5..=w).contains(&d.position.x) && (-0.5..=h).contains(&d.position.y));
    }
    dets
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model_fit(fit: InputFit, dynamic: bool) -> ModelFit {
        ModelFit {
            fit,
            input_width: 416,
            input_height: 320,
            auto_fit: dynamic.then_some(AutoFit {
                multiple: 32,
                pitch_min_px: 8.0,
                pitch_max_px: 20.0,
                pitch_target_px: 12.0,
                prefer_stretch: false,
            }),
        }
    }

    /// Only a whole-image stretch (chosen, or a fixed-input model's "auto") bounds the aspect ratio,
    /// and only the "auto" fit of a dynamic-input model follows the pitch.
    #[test]
    fn each_fit_gives_its_layout_and_aspect_bound() {
        let size = ImageSize {
            width: 640,
            height: 240,
        };
        let auto = model_fit(InputFit::Auto, true);
        assert_eq!(auto.stretch_to(), None);
        let rules = model_fit(InputFit::Auto, true).auto_fit.unwrap();
        assert_eq!(
            auto.layout(size, Some(20.0)),
            fit_layout(size, Some(20.0), 416, 320, &rules)
        );
        let fixed = model_fit(InputFit::Auto, false);
        assert!(fixed.auto().is_none());
        assert_eq!(fixed.stretch_to(), Some((416, 320)));
        assert_eq!(fixed.layout(size, Some(20.0)), InputLayout::stretch(416, 320));
        let stretch = model_fit(InputFit::Stretch, true);
        assert_eq!((stretch.auto(), stretch.stretch_to()), (None, Some((416, 320))));
        let pad = model_fit(InputFit::Pad, true);
        assert_eq!(pad.stretch_to(), None);
        let l = pad.layout(size, Some(20.0));
        assert_eq!(
            (l.scaled_width, l.scaled_height, l.offset_x, l.offset_y),
            (416, 156, 0, 82),
            "isotropic, centred in the nominal input"
        );
    }
}
