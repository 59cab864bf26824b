//! The network input from an 8-bit image in one pass: OpenCV's bilinear `resize` (`INTER_LINEAR`)
//! re-done bit for bit, fused with the planar RGB f32 conversion (`v / 255`; B, G, R to R, G, B, grey
//! replicated, alpha dropped); the margin around the resized image is filled with its median colour
//! ([`FILL_SAMPLE_STEP`]).
//!
//! Why a uniform margin: a mirrored one (OpenCV `BORDER_REFLECT_101`) completes a dot cut by the
//! border with its reflection into one whole phantom marker centred on the edge, and merges a whole
//! dot a few px from the edge with its reflection into one blob centred nearer the edge (a row of dots
//! 6 px from the bottom edge came out 4-5 px too low); a replicated one smears the edge row into
//! streaks. Against the median colour, the gel's background on a marker sensor, a cut dot stays a cut
//! dot, which the network was trained to see at the edges of its training crops.
//!
//! Why: OpenCV's resize, its border copy and a separate conversion pass each walk the whole image,
//! and together they were a large share of the pipeline's CPU time; one pass over the output rows
//! with planar intermediate rows reads and writes each pixel once, and the AVX-512 kernels read the
//! interleaved row directly (no split into channel rows). Figures:
//! `docs/experiments/localization-input-and-speed.md`. Bit for bit: the same fixed-point arithmetic as
//! OpenCV 4's `cv::hal::resize` for 8-bit images (`resizeGeneric_` with `HResizeLinear<uchar, int,
//! short>` and `VResizeLinear<uchar, int, short>`, whose scalar and SIMD paths agree):
//!
//! - taps: `f = float((d + 0.5) * scale - 0.5)`, `s = floor(f)`, weights
//!   `round_even((1 - (f - s)) * 2048)` and `round_even((f - s) * 2048)`; columns out of the image are
//!   clamped to its first or last with weight 1 (2048, 0), rows are clipped while their weights stay;
//! - horizontal (exact): `h = s0 * a0 + s1 * a1`;
//! - vertical: `((b0 * (h0 >> 4)) >> 16) + ((b1 * (h1 >> 4)) >> 16) + 2) >> 2`.
//!
//! OpenCV swaps in its area filter for a scale of exactly 2 in both directions; for 8-bit images that
//! filter's `(a + b + c + d + 2) >> 2` equals the bilinear formula at weights (1024, 1024). The
//! tests compare with `imgproc::resize` + `copy_make_border` on many sizes, both directions and
//! every channel count.

use crate::layout::InputLayout;
use crate::window::Window;

/// OpenCV's fixed-point weight scale of 8-bit bilinear resizing (`INTER_RESIZE_COEF_SCALE`).
const COEF_SCALE: f32 = 2048.0;

/// One output column's (or row's) two source taps and their fixed-point weights.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Tap {
    first: usize,
    second: usize,
    w0: i16,
    w1: i16,
}

/// OpenCV's `saturate_cast<short>(float)`: round half to even, then saturate.
fn weight(v: f32) -> i16 {
    v.round_ties_even()
        .clamp(f32::from(i16::MIN), f32::from(i16::MAX)) as i16
}

/// The taps of a `src`-long axis resized to `dst`, as `cv::hal::resize` computes them. `clamp_weights`:
/// the column rule (a tap outside the image is the edge pixel at full weight); rows keep their
/// fractional weights and only clip their indices.
fn taps(src: usize, dst: usize, clamp_weights: bool) -> Vec<Tap> {
    let scale = 1.0 / (dst as f64 / src as f64);
    let last = src as i64 - 1;
    (0..dst)
        .map(|d| {
            let f = ((d as f64 + 0.5) * scale - 0.5) as f32;
            let floor = f.floor();
            let mut frac = f - floor;
            let mut s = floor as i64;
            if clamp_weights && s < 0 {
                (s, frac) = (0, 0.0);
            }
            if clamp_weights && s >= last {
                (s, frac) = (last, 0.0);
            }
            let clip = |i: i64| i.clamp(0, last) as usize;
            Tap {
                first: clip(s),
                second: clip(s + 1),
                w0: weight((1.0 - frac) * COEF_SCALE),
                w1: weight(frac * COEF_SCALE),
            }
        })
        .collect()
}

/// The margin's colour is the median, per channel, of the resized image's pixels in every
/// `FILL_SAMPLE_STEP`-th row and column (from its first): a few thousand pixels decide it as well as
/// all of them would.
pub const FILL_SAMPLE_STEP: usize = 4;

/// 2^23: `x + ROUND_BY_ADDING` holds the nearest integer to `x` (0 <= x < 2^23) in its mantissa.
const ROUND_BY_ADDING: f32 = 8_388_608.0;

/// Adds one resized row's values (each `k / 255`) at every `FILL_SAMPLE_STEP`-th column (from its
/// first) to the histogram of grey levels.
fn sample_row(row: &[f32], histogram: &mut [u32; 256]) {
    for &v in row.iter().step_by(FILL_SAMPLE_STEP) {
        // v is k / 255 for a grey level k, so v * 255 lies within rounding of k, and adding 2^23
        // rounds it to k in the low mantissa bits (f32's unit in the last place at 2^23 is 1): no
        // `round` (a libm call) and no saturating float-to-integer cast per sample, which showed in
        // profiles of the preprocessing.
        histogram[((v * 255.0 + ROUND_BY_ADDING).to_bits() & 0xff) as usize] += 1;
    }
}

/// The lower median of the grey levels counted in `histogram`, as a value `k / 255`.
fn median_of(histogram: &[u32; 256]) -> f32 {
    let n: u32 = histogram.iter().sum();
    let rank = n.saturating_sub(1) / 2;
    let mut seen = 0;
    for (k, count) in histogram.iter().enumerate() {
        seen += count;
        if seen > rank {
            return f32::from(k as u8) / 255.0;
        }
    }
    0.0
}

/// What the preprocessing keeps between calls ([`crate::network::network_input`]): the taps of the
/// latest sizes, the source row split into channel rows, and two rows resized horizontally (planar,
/// `h >> 4` as i16: the only form the vertical pass reads), and which kernels it may use.
#[derive(Debug)]
pub struct ResizeScratch {
    /// Source width, height and channels, resized width and height the taps were made for.
    sizes: (usize, usize, usize, usize, usize),
    columns: Vec<Tap>,
    rows: Vec<Tap>,
    /// The columns in blocks of 8 for the SSSE3 kernel (`None`: scalar, e.g. a downscale beyond 2x
    /// whose 8 columns span more than 16 source pixels, or no SSSE3).
    blocks: Option<simd::Blocks>,
    /// The columns in blocks of 16 for the AVX-512 VBMI kernel, which takes each column's taps
    /// straight out of the interleaved row (`None`: the split and the SSSE3 or scalar kernel).
    wide: Option<simd::WideBlocks>,
    /// The widest kernels to use where the CPU has them (tests narrow it to check the others).
    kernels: Kernels,
    /// One source row, one channel row after another, each `width + 16` long (the SIMD kernel reads
    /// 16 bytes from a block's first column).
    split: Vec<u8>,
    /// Source row held by each of the two buffers.
    held: [Option<usize>; 2],
    /// Per buffer: the channel rows, each `nw` rounded up to [`ROW_MULTIPLE`] long.
    buffers: [Vec<i16>; 2],
    /// One output row of one channel, for the median colour's samples.
    row: Vec<f32>,
}

impl Default for ResizeScratch {
    /// Scratch that uses the widest kernels the CPU has.
    fn default() -> Self {
        Self::with_kernels(Kernels::Avx512)
    }
}

impl ResizeScratch {
    /// Scratch that uses at most `kernels` (narrower ones where the CPU lacks them); every kernel set
    /// gives the same bits.
    pub fn with_kernels(kernels: Kernels) -> Self {
        Self {
            sizes: (0, 0, 0, 0, 0),
            columns: Vec::new(),
            rows: Vec::new(),
            blocks: None,
            wide: None,
            kernels,
            split: Vec::new(),
            held: [None, None],
            buffers: [Vec::new(), Vec::new()],
            row: Vec::new(),
        }
    }
}

/// An 8-bit image as [`resize_into_planar`] reads it.
pub(crate) struct Image<'a> {
    /// Row-major interleaved pixels, no row padding.
    pub bytes: &'a [u8],
    pub width: usize,
    pub height: usize,
    /// 1 (grey), 3 (BGR) or 4 (BGRA).
    pub channels: usize,
}

/// Resizes `image` into `layout` (bilinear, exactly OpenCV's `INTER_LINEAR`), fills the rest of the
/// input with the resized image's median colour, and writes planar RGB f32 in [0, 1] into `plane`:
/// the whole input (3 x input pixels), or with `window` only that rectangle of it (3 x window
/// pixels), with the same values the whole input holds there. Rows the window does not reach are
/// resized only where the median colour samples them.
pub(crate) fn resize_into_planar(
    image: &Image,
    layout: &InputLayout,
    window: Option<&Window>,
    scratch: &mut ResizeScratch,
    plane: &mut [f32],
) {
    let (nw, nh) = (layout.scaled_width as usize, layout.scaled_height as usize);
    let (iw, ih) = (layout.input_width as usize, layout.input_height as usize);
    let (ox, oy) = (layout.offset_x as usize, layout.offset_y as usize);
    let (wx, wy, ww, wh) = window.map_or((0, 0, iw, ih), |w| {
        (w.x as usize, w.y as usize, w.width as usize, w.height as usize)
    });
    let hw = ww * wh;
    // Grey: one channel row, copied into the other two planes; BGRA's alpha is not read.
    let planes = if image.channels == 1 { 1 } else { 3 };
    let sizes = (image.width, image.height, image.channels, nw, nh);
    if scratch.sizes != sizes || scratch.columns.len() != nw {
        scratch.sizes = sizes;
        scratch.columns = taps(image.width, nw, true);
        scratch.rows = taps(image.height, nh, false);
        scratch.blocks = simd::Blocks::new(&scratch.columns).filter(|_| scratch.kernels >= Kernels::Sse);
        scratch.wide = simd::WideBlocks::new(&scratch.columns, image.channels, planes)
            .filter(|_| scratch.kernels >= Kernels::Avx512);
    }
    let (padded_width, row_len) = (image.width + 16, nw.div_ceil(ROW_MULTIPLE) * ROW_MULTIPLE);
    scratch.split.resize(planes * padded_width, 0);
    for b in &mut scratch.buffers {
        b.resize(planes * row_len, 0);
    }
    scratch.row.resize(nw, 0.0);
    scratch.held = [None, None];
    let stride = image.width * image.channels;
    // The window's part of each resized row: columns `c0..c1`, written from window column `dest`.
    let (first, last) = (ox.max(wx), (ox + nw).min(wx + ww));
    let (c0, c1, dest) = if first < last {
        (first - ox, last - ox, first - wx)
    } else {
        (0, 0, 0)
    };
    // Whether the window shows any of the margin, whose median colour then has to be found.
    let margin_shown = wx < ox || wy < oy || wx + ww > ox + nw || wy + wh > oy + nh;
    let mut histograms = [[0u32; 256]; 3];
    let ResizeScratch {
        columns,
        rows,
        blocks,
        wide,
        kernels,
        split,
        held,
        buffers,
        row,
        ..
    } = scratch;
    for (dy, tap) in rows.iter().enumerate() {
        let y = oy + dy;
        let shown = (wy..wy + wh).contains(&y);
        let sampled = margin_shown && dy % FILL_SAMPLE_STEP == 0;
        if !shown && !sampled {
            continue;
        }
        // The two source rows, each resized horizontally once (consecutive output rows share one).
        if held[0] != Some(tap.first) && held[1] == Some(tap.first) {
            buffers.swap(0, 1);
            held.swap(0, 1);
        }
        for (k, sy) in [(0, tap.first), (1, tap.second)] {
            if held[k] == Some(sy) {
                continue;
            }
            let src = &image.bytes[sy * stride..(sy + 1) * stride];
            held[k] = Some(sy);
            if let Some(ahead) = image.bytes.get((sy + 2) * stride..(sy + 3) * stride) {
                simd::prefetch(ahead);
            }
            if let Some(w) = wide {
                w.horizontal(src, &mut buffers[k], row_len);
                continue;
            }
            split_channels(src, image.channels, planes, padded_width, split, *kernels);
            for c in 0..planes {
                let source = &split[c * padded_width..(c + 1) * padded_width];
                let out = &mut buffers[k][c * row_len..(c + 1) * row_len];
                match blocks {
                    Some(b) => b.horizontal(source, out),
                    None => horizontal(source, columns, out),
                }
            }
        }
        for c in 0..planes {
            let h0 = &buffers[0][c * row_len..c * row_len + nw];
            let h1 = &buffers[1][c * row_len..c * row_len + nw];
            // Source channel c is B, G, R: planes R, G, B.
            let p = if planes == 1 { 0 } else { 2 - c };
            let at = p * hw + y.saturating_sub(wy) * ww + dest;
            if sampled {
                simd::vertical(h0, h1, tap.w0, tap.w1, row, *kernels);
                sample_row(row, &mut histograms[p]);
                if shown {
                    plane[at..at + c1 - c0].copy_from_slice(&row[c0..c1]);
                }
            } else {
                let out = &mut plane[at..at + c1 - c0];
                simd::vertical(&h0[c0..c1], &h1[c0..c1], tap.w0, tap.w1, out, *kernels);
            }
        }
    }
    // The window's margin: whole rows above and below the image, then left and right of it.
    if margin_shown {
        for (p, histogram) in histograms.iter().enumerate().take(planes) {
            let fill = median_of(histogram);
            for (r, line) in plane[p * hw..(p + 1) * hw].chunks_exact_mut(ww).enumerate() {
                let y = wy + r;
                if y < oy || y >= oy + nh {
                    line.fill(fill);
                } else {
                    line[..dest].fill(fill);
                    line[dest + c1 - c0..].fill(fill);
                }
            }
        }
    }
    if planes == 1 {
        let (grey, rest) = plane.split_at_mut(hw);
        rest[..hw].copy_from_slice(grey);
        rest[hw..2 * hw].copy_from_slice(grey);
    }
}

/// The kernels the preprocessing may use, narrowest first (each where the CPU has it; the wider ones
/// fall back to the narrower). All give the same bits: OpenCV's `INTER_LINEAR`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Kernels {
    /// Plain Rust.
    Scalar,
    /// SSE2 and SSSE3: 8 columns at a time from channel rows split out of the interleaved row.
    Sse,
    /// AVX-512 (F, BW, VBMI): 16 columns at a time straight from the interleaved row.
    Avx512,
}

impl Kernels {
    /// Whether this CPU has these kernels (else narrower ones run in their place).
    pub fn available(self) -> bool {
        match self {
            Kernels::Scalar => true,
            Kernels::Sse => simd::has_ssse3(),
            Kernels::Avx512 => simd::has_avx512_vbmi(),
        }
    }

    /// The name `gelstereo bench` prints.
    pub fn as_str(self) -> &'static str {
        match self {
            Kernels::Scalar => "scalar",
            Kernels::Sse => "SSE",
            Kernels::Avx512 => "AVX-512",
        }
    }
}

/// Length multiple of the horizontally resized channel rows: whole blocks of the widest kernel.
const ROW_MULTIPLE: usize = 16;

/// Splits one interleaved source row into `planes` channel rows of `padded_width` each (B, G, R;
/// grey: one).
fn split_channels(
    src: &[u8],
    channels: usize,
    planes: usize,
    padded_width: usize,
    split: &mut [u8],
    kernels: Kernels,
) {
    let width = src.len() / channels;
    if channels == 1 {
        split[..width].copy_from_slice(src);
        return;
    }
    if channels == 3 && simd::split_bgr(src, split, padded_width, kernels) {
        return;
    }
    let (b, rest) = split.split_at_mut(padded_width);
    let (g, r) = rest.split_at_mut(padded_width);
    for (i, px) in src.chunks_exact(channels).enumerate() {
        (b[i], g[i], r[i]) = (px[0], px[1], px[2]);
    }
    debug_assert_eq!(planes, 3);
}

/// One channel row resized horizontally (scalar): `h >> 4` of OpenCV's `h = s0 * a0 + s1 * a1`.
fn horizontal(row: &[u8], columns: &[Tap], out: &mut [i16]) {
    for (o, t) in out.iter_mut().zip(columns) {
        let h = i32::from(row[t.first]) * i32::from(t.w0) + i32::from(row[t.second]) * i32::from(t.w1);
        *o = (h >> 4) as i16;
    }
}

/// One output row of one channel from two horizontally resized rows (scalar): OpenCV's
/// `((b0 * h0) >> 16) + ((b1 * h1) >> 16) + 2) >> 2`, then `v / 255`.
fn vertical(h0: &[i16], h1: &[i16], b0: i16, b1: i16, out: &mut [f32]) {
    let (b0, b1) = (i32::from(b0), i32::from(b1));
    for ((o, &s0), &s1) in out.iter_mut().zip(h0).zip(h1) {
        let v = (((b0 * i32::from(s0)) >> 16) + ((b1 * i32::from(s1)) >> 16) + 2) >> 2;
        *o = f32::from(v.clamp(0, 255) as u8) / 255.0;
    }
}

/// The SIMD kernels (x86-64: SSE2, which every x86-64 CPU has, and SSSE3's byte shuffle, checked
/// at run time). The same integer arithmetic as the scalar kernels, 8 values at a time; the tests
/// check both paths against OpenCV.
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod simd {
    use std::arch::x86_64::{
        __m128i, _MM_HINT_T0, _mm_add_epi16, _mm_cvtepi32_ps, _mm_div_ps, _mm_loadu_si128, _mm_madd_epi16,
        _mm_mulhi_epi16, _mm_or_si128, _mm_packs_epi32, _mm_prefetch, _mm_set1_epi16, _mm_set1_ps,
        _mm_setzero_si128, _mm_shuffle_epi8, _mm_srai_epi16, _mm_srai_epi32, _mm_storeu_ps, _mm_storeu_si128,
        _mm_unpackhi_epi8, _mm_unpackhi_epi16, _mm_unpacklo_epi8, _mm_unpacklo_epi16, _mm256_add_epi16,
        _mm256_loadu_si256, _mm256_mulhi_epi16, _mm256_set1_epi16, _mm256_srai_epi16, _mm256_storeu_si256,
        _mm512_add_ps, _mm512_castsi512_si256, _mm512_cvtepi32_ps, _mm512_cvtepu16_epi32,
        _mm512_extracti64x4_epi64, _mm512_loadu_si512, _mm512_madd_epi16, _mm512_maskz_permutex2var_epi8,
        _mm512_mul_ps, _mm512_packs_epi32, _mm512_permutexvar_epi64, _mm512_set1_ps, _mm512_setr_epi64,
        _mm512_srai_epi32, _mm512_storeu_ps, _mm512_sub_ps,
    };

    use super::{Kernels, Tap};

    /// 16 bytes from the start of `s` (which must hold at least 16).
    fn load(s: &[u8]) -> __m128i {
        let s = &s[..16];
        // SAFETY: `s` holds 16 bytes (checked by the slice above); unaligned loads are allowed.
        unsafe { _mm_loadu_si128(s.as_ptr().cast()) }
    }

    /// 8 i16 from the start of `s` (which must hold at least 8).
    fn load_i16(s: &[i16]) -> __m128i {
        let s = &s[..8];
        // SAFETY: `s` holds 8 i16 = 16 bytes (checked by the slice above).
        unsafe { _mm_loadu_si128(s.as_ptr().cast()) }
    }

    /// The output columns in blocks of 8: the block's first source column (a 16-byte window of the
    /// channel row starts there), the byte shuffle that picks each column's two taps out of the
    /// window, and the weights in the same order, as `_mm_madd_epi16` pairs them.
    #[derive(Debug)]
    pub(super) struct Blocks {
        start: Vec<usize>,
        shuffle: Vec<[u8; 16]>,
        weights: Vec<[i16; 16]>,
    }

    impl Blocks {
        /// `None` without SSSE3, or when 8 consecutive columns span more than 15 source pixels.
        pub(super) fn new(columns: &[Tap]) -> Option<Self> {
            if !has_ssse3() || columns.is_empty() {
                return None;
            }
            let mut b = Self {
                start: Vec::new(),
                shuffle: Vec::new(),
                weights: Vec::new(),
            };
            for first in (0..columns.len()).step_by(8) {
                let start = columns[first].first;
                let (mut shuffle, mut weights) = ([0u8; 16], [0i16; 16]);
                for j in 0..8 {
                    // Columns past the end repeat the last one (written to the padding of `out`).
                    let t = columns[(first + j).min(columns.len() - 1)];
                    // The second tap is the next pixel or (at the right edge) has weight 0.
                    let offset = t.first - start;
                    if offset + 1 > 15 || (t.second != t.first + 1 && t.w1 != 0) {
                        return None;
                    }
                    shuffle[2 * j] = offset as u8;
                    shuffle[2 * j + 1] = offset as u8 + 1;
                    weights[2 * j] = t.w0;
                    weights[2 * j + 1] = t.w1;
                }
                b.start.push(start);
                b.shuffle.push(shuffle);
                b.weights.push(weights);
            }
            Some(b)
        }

        /// One channel row (`row` padded by 16 bytes past the image) resized horizontally into
        /// `out` (`h >> 4`, 8 columns per block; `out` holds whole blocks).
        pub(super) fn horizontal(&self, row: &[u8], out: &mut [i16]) {
            // SAFETY: `Blocks` exists only where SSSE3 was detected (`Blocks::new`).
            unsafe { self.horizontal_ssse3(row, out) }
        }

        #[target_feature(enable = "ssse3")]
        fn horizontal_ssse3(&self, row: &[u8], out: &mut [i16]) {
            let zero = _mm_setzero_si128();
            let blocks = self.start.iter().zip(&self.shuffle).zip(&self.weights);
            for (((&start, shuffle), weights), out) in blocks.zip(out.chunks_exact_mut(8)) {
                let pairs = _mm_shuffle_epi8(load(&row[start..]), load(shuffle));
                let lo = _mm_madd_epi16(_mm_unpacklo_epi8(pairs, zero), load_i16(weights));
                let hi = _mm_madd_epi16(_mm_unpackhi_epi8(pairs, zero), load_i16(&weights[8..]));
                let h = _mm_packs_epi32(_mm_srai_epi32(lo, 4), _mm_srai_epi32(hi, 4));
                // SAFETY: `out` (one chunk) holds 8 i16.
                unsafe { _mm_storeu_si128(out.as_mut_ptr().cast(), h) };
            }
        }
    }

    /// Whether the CPU has SSSE3 (the byte shuffle of the SSE kernels).
    pub(super) fn has_ssse3() -> bool {
        std::arch::is_x86_feature_detected!("ssse3")
    }

    /// Whether the CPU has the AVX-512 parts the wide kernels use (byte permutes across two
    /// registers: VBMI).
    pub(super) fn has_avx512_vbmi() -> bool {
        std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512vbmi")
    }

    /// Source bytes one wide block reads from its first column's first byte: two 64-byte registers,
    /// the table of one byte permute.
    const WIDE_SPAN: usize = 128;

    /// The output columns in blocks of 16 for AVX-512 VBMI: each block's two taps per column picked
    /// by byte permutes straight out of the interleaved row (one permute per channel, two channels
    /// per pack), so the row is never split into channels. Why: on a 640 x 480 BGR view the split and
    /// the SSSE3 kernel were two thirds of the preprocessing.
    #[derive(Debug)]
    pub(super) struct WideBlocks {
        /// Byte offset of each block's first source column in the row.
        start: Vec<usize>,
        /// Per block, per channel: the permute's indices, one per 16-bit lane (its even byte; the
        /// odd ones are zeroed by the permute's mask): each column's two taps side by side.
        index: Vec<[[u8; 64]; 3]>,
        /// Per block: the taps' weights in the same order, as `_mm512_madd_epi16` pairs them.
        weights: Vec<[i16; 32]>,
        planes: usize,
    }

    impl WideBlocks {
        /// `None` without AVX-512 VBMI, or when a block's taps lie more than [`WIDE_SPAN`] bytes
        /// from its first (a downscale beyond about 2.6x for BGR).
        pub(super) fn new(columns: &[Tap], channels: usize, planes: usize) -> Option<Self> {
            if !has_avx512_vbmi() || columns.is_empty() || !matches!(channels, 1 | 3 | 4) {
                return None;
            }
            let mut b = Self {
                start: Vec::new(),
                index: Vec::new(),
                weights: Vec::new(),
                planes,
            };
            for first in (0..columns.len()).step_by(16) {
                let start = columns[first].first;
                let (mut index, mut weights) = ([[0u8; 64]; 3], [0i16; 32]);
                for j in 0..16 {
                    // Columns past the end repeat the last one (written to the row's padding).
                    let t = columns[(first + j).min(columns.len() - 1)];
                    if t.second != t.first + 1 && t.w1 != 0 {
                        return None;
                    }
                    // A second tap of weight 0 at the right edge reads the first again.
                    let second = if t.second == t.first + 1 {
                        t.second
                    } else {
                        t.first
                    };
                    for (c, lanes) in index.iter_mut().enumerate().take(planes) {
                        let at = |x: usize| channels * (x - start) + c;
                        if at(second) >= WIDE_SPAN {
                            return None;
                        }
                        lanes[4 * j] = at(t.first) as u8;
                        lanes[4 * j + 2] = at(second) as u8;
                    }
                    weights[2 * j] = t.w0;
                    weights[2 * j + 1] = t.w1;
                }
                b.start.push(channels * start);
                b.index.push(index);
                b.weights.push(weights);
            }
            Some(b)
        }

        /// One interleaved source row resized horizontally into `out`: channel `c`'s row (`h >> 4`)
        /// at `c * row_len`, 16 columns per block (`row_len` holds whole blocks).
        pub(super) fn horizontal(&self, row: &[u8], out: &mut [i16], row_len: usize) {
            // SAFETY: `WideBlocks` exists only where AVX-512 F, BW and VBMI were detected.
            unsafe { self.horizontal_avx512(row, out, row_len) }
        }

        #[target_feature(enable = "avx512f,avx512bw,avx512vbmi,avx2")]
        fn horizontal_avx512(&self, row: &[u8], out: &mut [i16], row_len: usize) {
            let mut tail = [0u8; WIDE_SPAN];
            // Each 16-bit lane takes the byte its index's even byte points at, zero-extended.
            let even_bytes: u64 = 0x5555_5555_5555_5555;
            // `_mm512_packs_epi32` of two channels' 16 values interleaves them per 128-bit lane,
            // four at a time; these 64-bit moves put the first channel's back in the low half.
            let unlace = _mm512_setr_epi64(0, 2, 4, 6, 1, 3, 5, 7);
            let blocks = self.start.iter().zip(&self.index).zip(&self.weights);
            for (b, ((&start, index), weights)) in blocks.enumerate() {
                // The last blocks' spans run past the row: read them from a zero-padded copy.
                let span = match row.get(start..start + WIDE_SPAN) {
                    Some(span) => span,
                    None => {
                        let rest = &row[start.min(row.len())..];
                        tail[..rest.len()].copy_from_slice(rest);
                        tail[rest.len()..].fill(0);
                        &tail
                    }
                };
                // SAFETY: `span` holds 128 bytes, `weights` 64 (checked by their types and the
                // slicing above); unaligned loads are allowed.
                let (lo, hi, w) = unsafe {
                    (
                        _mm512_loadu_si512(span.as_ptr().cast()),
                        _mm512_loadu_si512(span[64..].as_ptr().cast()),
                        _mm512_loadu_si512(weights.as_ptr().cast()),
                    )
                };
                // `h >> 4` of channel c's 16 columns, as 16 i32.
                let channel = |c: usize| {
                    // SAFETY: `index[c]` holds 64 bytes.
                    let taps = _mm512_maskz_permutex2var_epi8(
                        even_bytes,
                        lo,
                        unsafe { _mm512_loadu_si512(index[c].as_ptr().cast()) },
                        hi,
                    );
                    _mm512_srai_epi32::<4>(_mm512_madd_epi16(taps, w))
                };
                // Channels in pairs (the last one, if odd, with itself, computed and stored once),
                // one pack per pair.
                for c in (0..self.planes).step_by(2) {
                    let next = (c + 1).min(self.planes - 1);
                    let first = channel(c);
                    let second = if next == c { first } else { channel(next) };
                    let both = _mm512_permutexvar_epi64(unlace, _mm512_packs_epi32(first, second));
                    let halves = [
                        (c, _mm512_castsi512_si256(both)),
                        (next, _mm512_extracti64x4_epi64::<1>(both)),
                    ];
                    for (k, half) in halves.into_iter().take(if next == c { 1 } else { 2 }) {
                        let d = &mut out[k * row_len + 16 * b..k * row_len + 16 * b + 16];
                        // SAFETY: `d` holds 16 i16 = 32 bytes (checked by the slice above).
                        unsafe { _mm256_storeu_si256(d.as_mut_ptr().cast(), half) };
                    }
                }
            }
        }
    }

    /// Asks the CPU to bring `bytes` into its cache (a source row two ahead of the one being
    /// resized): a frame is read once, mostly from memory, and without the hint the horizontal pass
    /// waits on each of a row's cache lines in turn.
    pub(super) fn prefetch(bytes: &[u8]) {
        for line in bytes.chunks(64) {
            // SAFETY: a prefetch only hints; the address lies inside `bytes`.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(line.as_ptr().cast()) };
        }
    }

    /// BGR row into three channel rows (`split`: B, G, R, each `padded_width` long), 16 pixels per
    /// step with SSSE3 shuffles; false (nothing done) without SSSE3 or when not allowed.
    pub(super) fn split_bgr(src: &[u8], split: &mut [u8], padded_width: usize, kernels: Kernels) -> bool {
        if kernels < Kernels::Sse || !has_ssse3() {
            return false;
        }
        // SAFETY: SSSE3 is present (checked above).
        unsafe { split_bgr_ssse3(src, split, padded_width) };
        true
    }

    /// `SPLIT_MASKS[c][part]` picks channel `c` of 16 BGR pixels out of their `part`-th 16 bytes
    /// (0x80: a zero byte).
    const SPLIT_MASKS: [[[u8; 16]; 3]; 3] = {
        let mut m = [[[0x80u8; 16]; 3]; 3];
        let mut c = 0;
        while c < 3 {
            let mut j = 0;
            while j < 16 {
                let byte = 3 * j + c;
                m[c][byte / 16][j] = (byte % 16) as u8;
                j += 1;
            }
            c += 1;
        }
        m
    };

    #[target_feature(enable = "ssse3")]
    fn split_bgr_ssse3(src: &[u8], split: &mut [u8], padded_width: usize) {
        let masks = SPLIT_MASKS.map(|m| m.map(|m| load(&m)));
        let width = src.len() / 3;
        let whole = width / 16;
        for (k, px) in src.chunks_exact(48).enumerate() {
            let v = [load(px), load(&px[16..]), load(&px[32..])];
            for (c, m) in masks.iter().enumerate() {
                let r = _mm_or_si128(
                    _mm_or_si128(_mm_shuffle_epi8(v[0], m[0]), _mm_shuffle_epi8(v[1], m[1])),
                    _mm_shuffle_epi8(v[2], m[2]),
                );
                let d = &mut split[c * padded_width + 16 * k..c * padded_width + 16 * k + 16];
                // SAFETY: `d` holds 16 bytes (checked by the slice above).
                unsafe { _mm_storeu_si128(d.as_mut_ptr().cast(), r) };
            }
        }
        for i in 16 * whole..width {
            for c in 0..3 {
                split[c * padded_width + i] = src[3 * i + c];
            }
        }
    }

    /// [`super::vertical`] 8 values at a time (SSE2: `_mm_mulhi_epi16` is OpenCV's
    /// `(b * h) >> 16` on i16, the division by 255 is IEEE like the scalar one).
    pub(super) fn vertical(h0: &[i16], h1: &[i16], b0: i16, b1: i16, out: &mut [f32], kernels: Kernels) {
        let n = out.len().min(h0.len()).min(h1.len());
        let mut done = 0;
        if kernels >= Kernels::Avx512 && has_avx512_vbmi() {
            done = n / 16 * 16;
            // SAFETY: AVX-512 F and BW are present (checked above).
            unsafe { vertical_avx512(&h0[..done], &h1[..done], b0, b1, &mut out[..done]) };
        }
        let whole = if kernels >= Kernels::Sse {
            done + (n - done) / 8 * 8
        } else {
            0
        };
        // SAFETY: SSE2 is part of every x86-64 CPU.
        unsafe { vertical_sse2(&h0[done..whole], &h1[done..whole], b0, b1, &mut out[done..whole]) };
        super::vertical(&h0[whole..n], &h1[whole..n], b0, b1, &mut out[whole..n]);
    }

    /// [`vertical_sse2`] 16 values at a time. `v / 255` without a division: `q = v * (1 / 255)` is
    /// off by at most one unit in the last place, and one correction step by the residual
    /// `v - 255 q` lands on the IEEE quotient for every `v` in 0..=255 (checked by a test). Why: the
    /// division was the dearest step of the vertical pass.
    #[target_feature(enable = "avx512f,avx512bw,avx2")]
    fn vertical_avx512(h0: &[i16], h1: &[i16], b0: i16, b1: i16, out: &mut [f32]) {
        let (w0, w1, two) = (_mm256_set1_epi16(b0), _mm256_set1_epi16(b1), _mm256_set1_epi16(2));
        let (inverse, scale) = (_mm512_set1_ps(1.0 / 255.0), _mm512_set1_ps(255.0));
        for ((o, s0), s1) in out
            .chunks_exact_mut(16)
            .zip(h0.chunks_exact(16))
            .zip(h1.chunks_exact(16))
        {
            // SAFETY: `s0`, `s1` (one chunk each) hold 16 i16 = 32 bytes.
            let (s0, s1) = unsafe {
                (
                    _mm256_loadu_si256(s0.as_ptr().cast()),
                    _mm256_loadu_si256(s1.as_ptr().cast()),
                )
            };
            let sum = _mm256_add_epi16(_mm256_mulhi_epi16(s0, w0), _mm256_mulhi_epi16(s1, w1));
            let v = _mm512_cvtepi32_ps(_mm512_cvtepu16_epi32(_mm256_srai_epi16::<2>(_mm256_add_epi16(
                sum, two,
            ))));
            let q = _mm512_mul_ps(v, inverse);
            let residual = _mm512_sub_ps(v, _mm512_mul_ps(q, scale));
            let q = _mm512_add_ps(q, _mm512_mul_ps(residual, inverse));
            // SAFETY: `o` (one chunk) holds 16 f32.
            unsafe { _mm512_storeu_ps(o.as_mut_ptr(), q) };
        }
    }

    #[target_feature(enable = "sse2")]
    fn vertical_sse2(h0: &[i16], h1: &[i16], b0: i16, b1: i16, out: &mut [f32]) {
        let (w0, w1, two, zero) = (
            _mm_set1_epi16(b0),
            _mm_set1_epi16(b1),
            _mm_set1_epi16(2),
            _mm_setzero_si128(),
        );
        let scale = _mm_set1_ps(255.0);
        for ((o, s0), s1) in out
            .chunks_exact_mut(8)
            .zip(h0.chunks_exact(8))
            .zip(h1.chunks_exact(8))
        {
            let sum = _mm_add_epi16(
                _mm_mulhi_epi16(load_i16(s0), w0),
                _mm_mulhi_epi16(load_i16(s1), w1),
            );
            let v = _mm_srai_epi16(_mm_add_epi16(sum, two), 2);
            let lo = _mm_div_ps(_mm_cvtepi32_ps(_mm_unpacklo_epi16(v, zero)), scale);
            let hi = _mm_div_ps(_mm_cvtepi32_ps(_mm_unpackhi_epi16(v, zero)), scale);
            // SAFETY: `o` (one chunk) holds 8 f32.
            unsafe {
                _mm_storeu_ps(o.as_mut_ptr(), lo);
                _mm_storeu_ps(o.as_mut_ptr().add(4), hi);
            }
        }
    }
}

/// Other targets: the scalar kernels only.
#[cfg(not(target_arch = "x86_64"))]
mod simd {
    use super::{Kernels, Tap};

    /// No cache hint on other targets.
    pub(super) fn prefetch(_: &[u8]) {}

    #[derive(Debug)]
    pub(super) enum Blocks {}

    impl Blocks {
        pub(super) fn new(_: &[Tap]) -> Option<Self> {
            None
        }

        pub(super) fn horizontal(&self, _: &[u8], _: &mut [i16]) {
            match *self {}
        }
    }

    pub(super) fn has_ssse3() -> bool {
        false
    }

    pub(super) fn has_avx512_vbmi() -> bool {
        false
    }

    #[derive(Debug)]
    pub(super) enum WideBlocks {}

    impl WideBlocks {
        pub(super) fn new(_: &[Tap], _: usize, _: usize) -> Option<Self> {
            None
        }

        pub(super) fn horizontal(&self, _: &[u8], _: &mut [i16], _: usize) {
            match *self {}
        }
    }

    pub(super) fn split_bgr(_: &[u8], _: &mut [u8], _: usize, _: Kernels) -> bool {
        false
    }

    pub(super) fn vertical(h0: &[i16], h1: &[i16], b0: i16, b1: i16, out: &mut [f32], _: Kernels) {
        super::vertical(h0, h1, b0, b1, out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{CV_8UC1, CV_8UC3, CV_8UC4, Mat, Scalar, Size};
    use opencv::imgproc;
    use opencv::prelude::*;

    /// A pseudo-random image (xorshift), so that every rounding path is hit.
    fn noise(w: i32, h: i32, typ: i32, seed: u64) -> Mat {
        let mut m = Mat::new_rows_cols_with_default(h, w, typ, Scalar::all(0.0)).expect("test image");
        let mut s = seed | 1;
        for v in m.data_bytes_mut().expect("bytes") {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            *v = (s >> 24) as u8;
        }
        m
    }

    fn layout(iw: u32, ih: u32, nw: u32, nh: u32, ox: u32, oy: u32) -> InputLayout {
        InputLayout {
            input_width: iw,
            input_height: ih,
            scaled_width: nw,
            scaled_height: nh,
            offset_x: ox,
            offset_y: oy,
        }
    }

    /// The reference: OpenCV's resize and copyMakeBorder, then `v / 255` into planar R, G, B.
    fn opencv_planar(image: &Mat, l: &InputLayout) -> Vec<f32> {
        let mut resized = Mat::default();
        let size = Size::new(l.scaled_width as i32, l.scaled_height as i32);
        imgproc::resize(image, &mut resized, size, 0.0, 0.0, imgproc::INTER_LINEAR).expect("resize");
        // The fill: per channel, the lower median of every 4th pixel of every 4th row, sorted.
        let n = resized.channels() as usize;
        let (nw, nh) = (l.scaled_width as usize, l.scaled_height as usize);
        let bytes = resized.data_bytes().expect("bytes");
        let mut fill = Scalar::default();
        for c in 0..n.min(3) {
            let mut values: Vec<u8> = (0..nh)
                .step_by(4)
                .flat_map(|y| (0..nw).step_by(4).map(move |x| (y, x)))
                .map(|(y, x)| bytes[(y * nw + x) * n + c])
                .collect();
            values.sort_unstable();
            fill[c] = f64::from(values[(values.len() - 1) / 2]);
        }
        let mut padded = Mat::default();
        let (top, left) = (l.offset_y as i32, l.offset_x as i32);
        let bottom = (l.input_height - l.scaled_height) as i32 - top;
        let right = (l.input_width - l.scaled_width) as i32 - left;
        opencv::core::copy_make_border(
            &resized,
            &mut padded,
            top,
            bottom,
            left,
            right,
            opencv::core::BORDER_CONSTANT,
            fill,
        )
        .expect("border");
        let n = padded.channels() as usize;
        let hw = (l.input_width * l.input_height) as usize;
        let bytes = padded.data_bytes().expect("bytes");
        let mut plane = vec![0.0f32; 3 * hw];
        for p in 0..hw {
            let px = &bytes[n * p..n * p + n];
            let rgb = if n == 1 { [px[0]; 3] } else { [px[2], px[1], px[0]] };
            for (c, v) in rgb.into_iter().enumerate() {
                plane[c * hw + p] = f32::from(v) / 255.0;
            }
        }
        plane
    }

    /// The fused pass equals OpenCV's resize + border + planar conversion bit for bit: downscales
    /// (the reference sensor into the fast and the shipped model's inputs), upscales (a GelSight
    /// Mini brought to the trained pitch), scale exactly 2 and 1, odd sizes, every channel count,
    /// margins filled with the median colour (wider than the image too).
    #[test]
    fn fused_resize_is_bit_identical_to_opencv() {
        let cases = [
            (640, 480, layout(416, 320, 406, 304, 5, 8)),
            (640, 480, layout(416, 416, 416, 416, 0, 0)),
            (640, 480, layout(320, 240, 320, 240, 0, 0)),
            (640, 480, layout(640, 480, 640, 480, 0, 0)),
            (800, 600, layout(512, 384, 501, 376, 6, 4)),
            (320, 240, layout(608, 448, 598, 448, 5, 0)),
            (320, 240, layout(640, 480, 579, 434, 30, 23)),
            (37, 29, layout(64, 48, 59, 47, 2, 1)),
            (33, 31, layout(40, 40, 12, 10, 14, 15)),
        ];
        for kernels in [Kernels::Avx512, Kernels::Sse, Kernels::Scalar] {
            let mut scratch = ResizeScratch::with_kernels(kernels);
            for (k, &(w, h, l)) in cases.iter().enumerate() {
                for (typ, channels) in [(CV_8UC3, 3), (CV_8UC1, 1), (CV_8UC4, 4)] {
                    let img = noise(w, h, typ, 17 + k as u64);
                    let want = opencv_planar(&img, &l);
                    let mut got = vec![-1.0f32; want.len()];
                    let image = Image {
                        bytes: img.data_bytes().expect("bytes"),
                        width: w as usize,
                        height: h as usize,
                        channels,
                    };
                    resize_into_planar(&image, &l, None, &mut scratch, &mut got);
                    let bad = got
                        .iter()
                        .zip(&want)
                        .position(|(a, b)| a.to_bits() != b.to_bits());
                    assert_eq!(bad, None, "{w}x{h}, {channels} channel(s), {l:?}, {kernels:?}");
                }
            }
        }
    }

    /// Every grey level comes out of the vertical pass as the IEEE quotient `k / 255` with each
    /// kernel (the widest one multiplies by the inverse and corrects by the residual).
    #[test]
    fn the_vertical_pass_divides_every_grey_level_exactly() {
        // h = 128 k with row weights (2048, 0) gives back k.
        let h0: Vec<i16> = (0..256).map(|k| 128 * k).collect();
        let h1 = vec![0i16; 256];
        let want: Vec<u32> = (0..=255u8).map(|k| (f32::from(k) / 255.0).to_bits()).collect();
        for kernels in [Kernels::Avx512, Kernels::Sse, Kernels::Scalar] {
            let mut got = vec![-1.0f32; 256];
            simd::vertical(&h0, &h1, 2048, 0, &mut got, kernels);
            let got: Vec<u32> = got.iter().map(|v| v.to_bits()).collect();
            assert_eq!(got, want, "{kernels:?}");
        }
    }

    /// A window of the input holds exactly the values the whole input holds there, the margin's
    /// median colour (the whole image's) included: windows inside the image, over its margins, past
    /// its last rows, and the whole input, for grey, BGR and BGRA, with and without SIMD.
    #[test]
    fn a_window_holds_the_whole_inputs_values() {
        let l = layout(416, 320, 406, 304, 5, 8);
        let windows = [
            Window {
                x: 64,
                y: 0,
                width: 288,
                height: 320,
            },
            Window {
                x: 96,
                y: 64,
                width: 224,
                height: 192,
            },
            Window {
                x: 0,
                y: 288,
                width: 416,
                height: 32,
            },
            Window {
                x: 384,
                y: 0,
                width: 32,
                height: 320,
            },
            Window {
                x: 0,
                y: 0,
                width: 416,
                height: 320,
            },
        ];
        for kernels in [Kernels::Avx512, Kernels::Sse, Kernels::Scalar] {
            let mut scratch = ResizeScratch::with_kernels(kernels);
            for (typ, channels) in [(CV_8UC3, 3), (CV_8UC1, 1), (CV_8UC4, 4)] {
                // Noise over a vertical ramp: the median of a few rows is not the whole image's.
                let mut img = noise(640, 480, typ, 5);
                let row_len = 640 * channels;
                for (y, row) in img
                    .data_bytes_mut()
                    .expect("bytes")
                    .chunks_exact_mut(row_len)
                    .enumerate()
                {
                    for v in row {
                        *v = (*v / 4).saturating_add((y / 2) as u8);
                    }
                }
                let image = Image {
                    bytes: img.data_bytes().expect("bytes"),
                    width: 640,
                    height: 480,
                    channels,
                };
                let (iw, hw) = (416usize, 416 * 320);
                let mut whole = vec![-1.0f32; 3 * hw];
                resize_into_planar(&image, &l, None, &mut scratch, &mut whole);
                for w in &windows {
                    let (x, y, ww, wh) = (w.x as usize, w.y as usize, w.width as usize, w.height as usize);
                    let mut got = vec![-1.0f32; 3 * ww * wh];
                    resize_into_planar(&image, &l, Some(w), &mut scratch, &mut got);
                    for (c, plane) in got.chunks_exact(ww * wh).enumerate() {
                        for (r, line) in plane.chunks_exact(ww).enumerate() {
                            let from = c * hw + (y + r) * iw + x;
                            let want = &whole[from..from + ww];
                            assert!(
                                line.iter().zip(want).all(|(a, b)| a.to_bits() == b.to_bits()),
                                "{w:?}, {channels} channel(s), plane {c}, row {r}, {kernels:?}"
                            );
                        }
                    }
                }
            }
        }
    }
}
