//! Marknet's network: preprocessing an image into its input layout (`docs/model-contract.md`) and
//! running a batch of images through the ONNX session ([`Network::run_batch`]), with the checks of
//! the model at load and of each run's output.
//!
//! Preprocessing: the image is resized with OpenCV's bilinear `INTER_LINEAR` (half-pixel centres)
//! into an [`InputLayout`], converted to planar RGB f32 in [0, 1] (grey replicated, BGRA's alpha
//! dropped), the rest of the input filled with its median colour.

use std::path::{Path, PathBuf};

use gelstereo_core::ImageSize;
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual};
use ort::session::Session;
use ort::value::TensorRef;
use rayon::iter::{IntoParallelIterator, ParallelIterator};

use crate::contract::{MARKNET_INPUT, MARKNET_OUTPUT};
use crate::layout::{InputLayout, MAX_INPUT_SIDE_PX, layout_geometry};
use crate::onnx::{Opened, SessionOptions, check_finite, onnx_err, open_session};
use crate::postprocess::DecodeGeometry;
use crate::resize::{Image, ResizeScratch, resize_into_planar};
use crate::window::Window;
use crate::{Error, MarknetContract, Result, check_image, cv_err};

/// Marknet's network: its session and contract, and the buffers its runs reuse.
pub(crate) struct Network {
    /// The model file.
    pub(crate) path: PathBuf,
    /// The model's declared contract.
    pub(crate) contract: MarknetContract,
    session: Session,
    /// Scratch of each batch slot's preprocessing.
    resize: Vec<ResizeScratch>,
    /// The batch's input tensor.
    input: Vec<f32>,
}

impl Network {
    /// Loads `path`, checks its contract and runs it once on a grey image ([`probe_marknet`]).
    pub(crate) fn load(path: &Path, options: &SessionOptions) -> Result<Self> {
        let Opened {
            mut session,
            metadata: meta,
            inputs,
            outputs,
        } = open_session(path, options)?;
        let contract = MarknetContract::from_model(path, &meta, &inputs, &outputs)?;
        probe_marknet(path, &mut session, &contract)?;
        Ok(Self {
            path: path.to_path_buf(),
            contract,
            session,
            resize: Vec::new(),
            input: Vec::new(),
        })
    }

    /// Runs the network once on `images` under `layouts` (each on the whole input, or on the window
    /// `windows` gives), all of one input size; returns the raw output (`[Gy, Gx, m, 3]` logits per
    /// image, row-major, concatenated), in the spans `marknet.preprocess` and `marknet.network`.
    /// `stretch_to`: the input a whole-image stretch must keep the aspect ratio of
    /// ([`check_aspect`]); `parallel`: the images are preprocessed on rayon's thread pool.
    pub(crate) fn run_batch(
        &mut self,
        images: &[&Mat],
        windows: &[Option<Window>],
        layouts: &[InputLayout],
        stretch_to: Option<(u32, u32)>,
        parallel: bool,
    ) -> Result<Vec<f32>> {
        let Some(first) = layouts.first() else {
            return Ok(Vec::new());
        };
        let (iw, ih) = input_dims(first, windows.first().and_then(Option::as_ref));
        let (iw, ih) = (iw as usize, ih as usize);
        let preprocessing = tracing::trace_span!("marknet.preprocess").entered();
        self.input.resize(images.len() * 3 * iw * ih, 0.0);
        if self.resize.len() < images.len() {
            self.resize.resize_with(images.len(), ResizeScratch::default);
        }
        let slots = images
            .iter()
            .zip(windows)
            .zip(layouts)
            .zip(self.input.chunks_exact_mut(3 * iw * ih))
            .zip(self.resize.iter_mut())
            .collect();
        map_images(
            parallel,
            slots,
            |((((image, window), layout), plane), scratch)| {
                preprocess(image, layout, window.as_ref(), stretch_to, scratch, plane)
            },
        )
        .into_iter()
        .collect::<Result<()>>()?;
        drop(preprocessing);
        let _network = tracing::trace_span!("marknet.network").entered();
        let run = onnx_err(&self.path, "inference");
        let input = TensorRef::from_array_view(([images.len(), 3, ih, iw], self.input.as_slice()))
            .map_err(|e| run(e.to_string()))?;
        let outputs = self
            .session
            .run(ort::inputs![MARKNET_INPUT => input])
            .map_err(|e| run(e.to_string()))?;
        let (shape, raw) = outputs[MARKNET_OUTPUT]
            .try_extract_tensor::<f32>()
            .map_err(|e| run(e.to_string()))?;
        let c = &self.contract;
        let (gy, gx) = (ih / c.stride as usize, iw / c.stride as usize);
        let per_image = gy * gx * c.candidates as usize * 3;
        if raw.len() != per_image * images.len() {
            return Err(run(format!(
                "output '{MARKNET_OUTPUT}' has shape {shape}, expected [{}, {gy}, {gx}, {}, 3]",
                images.len(),
                c.candidates
            )));
        }
        check_finite(raw, MARKNET_OUTPUT).map_err(run)?;
        Ok(raw.to_vec())
    }

    /// The decoding geometry of an image of `size` under `layout`.
    pub(crate) fn geometry_for(&self, size: ImageSize, layout: &InputLayout) -> DecodeGeometry {
        layout_geometry(size, layout, self.contract.stride, self.contract.candidates)
    }

    /// [`geometry_for`](Self::geometry_for) of the network run on `window` of the layout's input.
    pub(crate) fn window_geometry(
        &self,
        size: ImageSize,
        layout: &InputLayout,
        window: Option<&Window>,
    ) -> DecodeGeometry {
        let whole = self.geometry_for(size, layout);
        let Some(w) = window else { return whole };
        let stride = self.contract.stride;
        DecodeGeometry {
            grid_y: (w.height / stride) as usize,
            grid_x: (w.width / stride) as usize,
            offset_x: whole.offset_x - f64::from(w.x),
            offset_y: whole.offset_y - f64::from(w.y),
            ..whole
        }
    }
}

/// Largest accepted ratio between an image's aspect ratio and the network input's: beyond it the resize
/// squashes markers into shapes far from anything the network was trained on.
pub const MAX_ASPECT_DISTORTION: f64 = 2.0;

/// Below this scale (output px per original px, along either axis) the image is first reduced to its
/// scaled size by area averaging (OpenCV `INTER_AREA`; `AREA_BELOW_SCALE` in the trainer), then
/// placed as usual: bilinear sampling reads 2 x 2 pixels per output pixel, so a reduction of 3x or
/// more skips most pixels, and scan lines or dots a few pixels wide alias into stripes and blobs (a
/// 1280 x 720 gel of bright 25 px dots at a 90 px pitch under scan-line banding, run at 0.13 x: 54 of
/// its 64 dots with bilinear sampling, all 64 and nothing else with area averaging;
/// `bright_dots_under_scan_lines_reduced_a_lot_are_found_and_the_banding_is_not`). Milder reductions
/// stay bilinear, as the network's training crops are: area averaging blurs small dots that
/// bilinear sampling keeps sharp (a higher threshold cost a real sensor markers in contact).
pub const AREA_BELOW_SCALE: f64 = 0.34;

/// Runs Marknet once on a mid-grey input and checks every output is finite: NaN or infinite
/// weights make a model useless on every frame, so they are an error at load (naming the model)
/// rather than a flag on each frame. The input is the smallest a dynamic-input model takes (two of
/// its size multiples a side, so the probe costs little), else the declared size.
fn probe_marknet(path: &Path, session: &mut Session, contract: &MarknetContract) -> Result<()> {
    let (w, h) = match contract.auto_fit {
        Some(fit) => (2 * fit.multiple as usize, 2 * fit.multiple as usize),
        None => (contract.input_width as usize, contract.input_height as usize),
    };
    let grey = vec![0.5f32; 3 * w * h];
    let run = onnx_err(path, "a check run at load");
    let input =
        TensorRef::from_array_view(([1, 3, h, w], grey.as_slice())).map_err(|e| run(e.to_string()))?;
    let outputs = session
        .run(ort::inputs![MARKNET_INPUT => input])
        .map_err(|e| run(e.to_string()))?;
    let (_, raw) = outputs[MARKNET_OUTPUT]
        .try_extract_tensor::<f32>()
        .map_err(|e| run(e.to_string()))?;
    check_finite(raw, MARKNET_OUTPUT).map_err(|m| run(format!("{m} (on a grey image)")))
}

/// Checks that an image's aspect ratio is within [`MAX_ASPECT_DISTORTION`] of the network input's
/// (the contract's whole-image stretch would distort markers beyond what training covered).
pub(crate) fn check_aspect(size: ImageSize, input_width: u32, input_height: u32) -> Result<()> {
    let img = f64::from(size.width) / f64::from(size.height);
    let net = f64::from(input_width) / f64::from(input_height);
    let ratio = if img > net { img / net } else { net / img };
    if ratio > MAX_ASPECT_DISTORTION {
        return Err(Error::Image {
            property: "size",
            expected: format!(
                "an aspect ratio within {MAX_ASPECT_DISTORTION}x of the network input {input_width}x{input_height}"
            ),
            found: format!("{}x{}", size.width, size.height),
        });
    }
    Ok(())
}

/// Resizes `image` into `layout` (OpenCV bilinear `INTER_LINEAR` on the 8-bit pixels: half-pixel
/// centres, no antialiasing; the margin filled with the resized image's median colour) and writes it
/// into `plane` as planar RGB f32 in [0, 1] (grey replicated, alpha dropped), in one pass
/// bit-identical to OpenCV's resize + copyMakeBorder with that constant ([`crate::resize`]); with
/// `window`, only that rectangle of the input (`plane` holds 3 x its pixels). `scratch` is kept
/// between calls.
pub(crate) fn write_layout(
    image: &Mat,
    layout: &InputLayout,
    window: Option<&Window>,
    scratch: &mut ResizeScratch,
    plane: &mut [f32],
) -> Result<()> {
    let owned;
    let image = if image.is_continuous() {
        image
    } else {
        owned = image
            .try_clone()
            .map_err(cv_err("copy of a non-continuous image"))?;
        &owned
    };
    let size = check_image(image)?;
    let reduced;
    let image = if f64::from(layout.scaled_width) < AREA_BELOW_SCALE * f64::from(size.width)
        || f64::from(layout.scaled_height) < AREA_BELOW_SCALE * f64::from(size.height)
    {
        let mut out = Mat::default();
        let to = opencv::core::Size::new(layout.scaled_width as i32, layout.scaled_height as i32);
        opencv::imgproc::resize(image, &mut out, to, 0.0, 0.0, opencv::imgproc::INTER_AREA)
            .map_err(cv_err("area reduction of a large image"))?;
        reduced = out;
        &reduced
    } else {
        image
    };
    let view = Image {
        bytes: image.data_bytes().map_err(cv_err("image data"))?,
        width: image.cols() as usize,
        height: image.rows() as usize,
        channels: image.channels() as usize,
    };
    resize_into_planar(&view, layout, window, scratch, plane);
    Ok(())
}

/// The network input of `image` under `layout`, as Marknet feeds its network: the image resized
/// (OpenCV's `INTER_LINEAR` bit for bit, area averaging first below 0.34 x), the rest of the input
/// filled with its median colour, planar RGB f32 in [0, 1] (3 x input pixels) in `plane`. `scratch`
/// is kept between calls and chooses the kernels ([`ResizeScratch::with_kernels`]); every kernel set
/// gives the same bits. For looking at what the network sees and for timing the kernels
/// (`gelstereo bench`).
pub fn network_input(
    image: &Mat,
    layout: &InputLayout,
    scratch: &mut ResizeScratch,
    plane: &mut Vec<f32>,
) -> Result<()> {
    // The image itself is checked by `write_layout`.
    let l = layout;
    let fits = |offset: u32, scaled: u32, input: u32| {
        scaled >= 1
            && input <= MAX_INPUT_SIDE_PX
            && offset.checked_add(scaled).is_some_and(|end| end <= input)
    };
    if !fits(l.offset_x, l.scaled_width, l.input_width) || !fits(l.offset_y, l.scaled_height, l.input_height)
    {
        return Err(Error::Image {
            property: "layout",
            expected: format!(
                "a resized image of at least 1 x 1 px inside a network input of at most {MAX_INPUT_SIDE_PX} px a side"
            ),
            found: format!("{l:?}"),
        });
    }
    plane.clear();
    plane.resize(3 * l.input_width as usize * l.input_height as usize, 0.0);
    write_layout(image, layout, None, scratch, plane)
}

/// Checks `image` and writes it into `plane` under `layout` ([`write_layout`]); `stretch_to`: the
/// network input a whole-image stretch must keep the aspect ratio of ([`check_aspect`]).
///
/// The trainer divides by 255 before resizing; resizing the 8-bit image first differs by at most
/// half a grey level (rounding), which `docs/model-contract.md` allows, and halves the cost.
fn preprocess(
    image: &Mat,
    layout: &InputLayout,
    window: Option<&Window>,
    stretch_to: Option<(u32, u32)>,
    scratch: &mut ResizeScratch,
    plane: &mut [f32],
) -> Result<()> {
    let size = check_image(image)?;
    if let Some((w, h)) = stretch_to {
        check_aspect(size, w, h)?;
    }
    write_layout(image, layout, window, scratch, plane)
}

/// The input size an image runs at: its layout's, or its window's.
pub(crate) fn input_dims(layout: &InputLayout, window: Option<&Window>) -> (u32, u32) {
    window.map_or((layout.input_width, layout.input_height), |w| (w.width, w.height))
}

/// `items` mapped by `f`, in order: on rayon's thread pool when `parallel` and there are several
/// (the images of a batch), else on the calling thread.
pub(crate) fn map_images<T: Send, R: Send>(
    parallel: bool,
    items: Vec<T>,
    f: impl Fn(T) -> R + Sync + Send,
) -> Vec<R> {
    if parallel && items.len() > 1 {
        items.into_par_iter().map(f).collect()
    } else {
        items.into_iter().map(f).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Kernels;
    use opencv::core::{CV_8UC1, CV_8UC3, CV_8UC4, Scalar};
    use opencv::prelude::*;

    /// Every pixel value at every channel position, converted exactly as `v / 255` into the right
    /// plane (B, G, R swapped to R, G, B; grey replicated; alpha dropped) when the image is the
    /// input's size.
    #[test]
    fn planar_rgb_is_exact_for_grey_bgr_and_bgra() -> Result<()> {
        for (typ, n) in [(CV_8UC1, 1usize), (CV_8UC3, 3), (CV_8UC4, 4)] {
            let (w, h) = (37, 29);
            let mut m =
                Mat::new_rows_cols_with_default(h, w, typ, Scalar::all(0.0)).map_err(cv_err("test"))?;
            for (i, v) in m.data_bytes_mut().map_err(cv_err("test"))?.iter_mut().enumerate() {
                *v = (i * 7 % 256) as u8;
            }
            let bytes = m.data_bytes().map_err(cv_err("test"))?.to_vec();
            let hw = (w * h) as usize;
            let mut plane = vec![-1.0f32; 3 * hw];
            let same = InputLayout::stretch(w as u32, h as u32);
            write_layout(&m, &same, None, &mut ResizeScratch::default(), &mut plane)?;
            for p in 0..hw {
                let px = &bytes[n * p..n * p + n];
                let (r, g, b) = if n == 1 {
                    (px[0], px[0], px[0])
                } else {
                    (px[2], px[1], px[0])
                };
                for (c, v) in [r, g, b].into_iter().enumerate() {
                    assert_eq!(
                        plane[c * hw + p].to_bits(),
                        (v as f32 / 255.0).to_bits(),
                        "{n} channels, px {p}"
                    );
                }
            }
        }
        Ok(())
    }

    /// `network_input` gives the same bits with every kernel set and refuses a layout whose resized
    /// image does not fit its input, naming the layout.
    #[test]
    fn the_network_input_is_the_same_with_every_kernel_set_and_a_bad_layout_is_refused() -> Result<()> {
        let mut m =
            Mat::new_rows_cols_with_default(480, 640, CV_8UC3, Scalar::all(0.0)).map_err(cv_err("test"))?;
        for (i, v) in m.data_bytes_mut().map_err(cv_err("test"))?.iter_mut().enumerate() {
            *v = (i * 31 % 253) as u8;
        }
        let layout = InputLayout {
            input_width: 416,
            input_height: 320,
            scaled_width: 406,
            scaled_height: 304,
            offset_x: 5,
            offset_y: 8,
        };
        let mut inputs = Vec::new();
        for kernels in [Kernels::Avx512, Kernels::Sse, Kernels::Scalar] {
            let mut plane = Vec::new();
            network_input(&m, &layout, &mut ResizeScratch::with_kernels(kernels), &mut plane)?;
            assert_eq!(plane.len(), 3 * 416 * 320);
            inputs.push(plane.iter().map(|v| v.to_bits()).collect::<Vec<u32>>());
        }
        assert!(inputs.windows(2).all(|w| w[0] == w[1]));
        let too_wide = InputLayout {
            offset_x: 20,
            ..layout
        };
        let err = network_input(&m, &too_wide, &mut ResizeScratch::default(), &mut Vec::new())
            .expect_err("a resized image past the input's edge");
        assert!(err.to_string().contains("image layout"), "{err}");
        Ok(())
    }
}
