//! The stride-1 "same" 3D convolution (`padding = k / 2`) and its two gradients, as direct
//! convolutions written for MFuseNet's shapes (1–16 input channels, 4 output channels, kernels
//! 3, 5 and 7): the input is copied once into a zero-padded buffer cut into tiles of 48 columns
//! (each tile's rows short and contiguous, with their halo), then every output row is computed in
//! blocks of 24 columns with the four output channels' accumulators held in registers (12 AVX
//! vectors): per kernel tap, three unaligned loads feed twelve fused multiply-adds (for kernels 3
//! and 5 written out in assembly, [`super::fma_kernel`], where LLVM's loop spilled the
//! accumulators; on a host with AVX-512F both blocks of a tile at once on 512-bit vectors,
//! [`super::wide_kernel`], for every kernel size, with the same bits). Work is split over
//! (channel group, depth plane) pairs with rayon, each writing its output planes in place.
//!
//! Measured on 2 AMD EPYC vCPUs (`cargo run --release -p fuse --example conv_speed`), k7 with
//! 8 → 4 channels on 32 × 372 × 428: 81 GFLOP/s with whole-width rows (an output block's 392
//! input rows 1.75 KB apart, each on its own page), 140–160 with the tiles.
//!
//! A layer can also write its output straight into the padded tiles of the layer that reads it
//! ([`conv3d_padded`], [`ConvInput::Padded`]): MFuseNet's feature tower and `concat` then make no
//! padded copies (about 13 % of the method's time at 960×540 before, all of it memory traffic).
//! The padded buffers a layer frees are kept (two per thread) for the next layer's padded input
//! or output, which then zeroes only its border: neither a whole-buffer `memset` nor fresh pages
//! faulted in and cleared by the kernel, per layer, at over 100 MB each.
//!
//! [`conv3d_with`] adds an epilogue for inference: the ReLU after a folded BatchNorm, and stride
//! 2 computed on the kept planes and rows only. In training the stride-2 convolution is this
//! convolution sampled at even positions ([`Tensor::subsample2`]); the stride-2 transposed
//! convolution (kernel 3, padding 1, output padding 1) is this convolution of the zero-upsampled
//! input with the kernel flipped and its channels swapped ([`transposed_as_conv`]); both run at
//! the coarse levels of the U-Net, about 3 % of the work.

use std::ops::Range;

use rayon::prelude::*;
use wide::f32x8;

use super::Tensor;
use super::amx_kernel;
use super::bf16_kernel;
use super::fma_kernel::{self, ACCUMULATORS};
use super::int16_kernel;
use super::wide_kernel;

/// Lanes of one vector.
const LANES: usize = 8;
/// Vectors per output block: 24 columns × 4 channels = 12 accumulators.
const VECTORS: usize = 3;
/// Output columns per block.
const BLOCK: usize = LANES * VECTORS;
/// Output channels computed together.
const GROUP: usize = 4;
/// Blocks per column tile of one job (48 columns).
const TILE_BLOCKS: usize = 2;
// A tile is one block of the 512-bit kernel.
const _: () = assert!(TILE_BLOCKS * BLOCK == wide_kernel::COLUMNS);

/// A zero-padded copy of a tensor cut into column tiles: `[tile][d + 2p][h + 2p][c][row]`, the
/// value of `(c, z, y, x)` at `(x / step, z + p, y + p, c, x % step + p)` and, within `K − 1`
/// columns of a tile's right edge, in the next tile's left halo too. `row` (≥ `step + 2p`) is a
/// tile's row length. One tile as wide as the tensor is a plain padded copy. The channels of a
/// row lie side by side: the `K²` rows of every channel that an output row reads are `K` runs
/// of `K · c` contiguous rows, and a layer writes its channels' rows of a plane as one run
/// (against `c · K` runs and `c` scattered streams with each channel's plane apart: at full size,
/// where every layer's tensor is far beyond the caches, the 3³ layers ran at a third of the
/// FMA peak).
struct Padded {
    data: Vec<f32>,
    channels: usize,
    depth: usize,
    height: usize,
    row: usize,
    /// The tensor's own `[c, d, h, w]`.
    shape: [usize; 4],
    /// The zero border in each dimension (`K / 2` of the kernel it was made for).
    p: usize,
    /// Columns per tile.
    step: usize,
    /// Rewritten as pairs for [`super::bf16_kernel`] or [`super::int16_kernel`] (shifted pairs
    /// of taps, or channel pairs): no longer the tensor's values, and the border no longer zero
    /// (a zero beside a value pairs with it).
    pairs: bool,
    /// Written by the layer before as bfloat16 channel pairs for a layer that pairs channels
    /// ([`conv3d_padded_pairs`]): that layer's rewrite is already done (`pairs` is set too).
    channel_pairs: bool,
}

impl Padded {
    fn new(x: &Tensor, p: usize, row: usize) -> Self {
        let w = x.shape[3];
        Self::tiled(x, p, w.max(1), row)
    }

    /// Tiles of `step` columns (the last may be narrower), each row `row` long.
    fn tiled(x: &Tensor, p: usize, step: usize, row: usize) -> Self {
        let [_, _, h, w] = x.shape;
        Self::tiled_window(x, (0..h, 0..w), p, step, row)
    }

    /// [`Padded::tiled`] of the `rows × columns` window of `x` (clamped to it), as if cropped.
    fn tiled_window(
        x: &Tensor,
        (rows, columns): (Range<usize>, Range<usize>),
        p: usize,
        step: usize,
        row: usize,
    ) -> Self {
        let [c, d, full_h, full_w] = x.shape;
        let (y0, x0) = (rows.start.min(full_h), columns.start.min(full_w));
        let (h, w) = (
            rows.end.min(full_h).saturating_sub(y0),
            columns.end.min(full_w).saturating_sub(x0),
        );
        let shape = [c, d, h, w];
        let (depth, height) = (d + 2 * p, h + 2 * p);
        let tiles = w.div_ceil(step).max(1);
        let layout = Layout { shape, p, step, row };
        let (mut data, dirty) = spare_buffer(tiles * c * depth * height * row, layout);
        // One padded plane per task, written in every tile: each source row is read once, from
        // its start to its end, and its columns copied into each tile that holds them (one task
        // per (tile, plane) read each row once per tile, a short run per row a plane apart, and
        // that read, waiting on memory, was about a tenth of MFuseNet's time on the demo's
        // capture).
        let block_len = (height * c * row).max(1);
        let mut blocks: Vec<Option<&mut [f32]>> = data.chunks_mut(block_len).map(Some).collect();
        let planes: Vec<(usize, Vec<&mut [f32]>)> = (0..depth)
            .map(|zz| {
                let in_tiles = (0..tiles)
                    .filter_map(|t| blocks.get_mut(t * depth + zz).and_then(Option::take))
                    .collect();
                (zz, in_tiles)
            })
            .collect();
        let spans: Vec<(usize, usize, usize)> = (0..tiles).map(|t| layout.columns(t)).collect();
        planes.into_par_iter().for_each(|(zz, mut in_tiles)| {
            if dirty {
                for (t, dst) in in_tiles.iter_mut().enumerate() {
                    layout.zero_border(dst, t, zz);
                }
            }
            if zz < p || zz >= d + p {
                return;
            }
            let z = zz - p;
            for y in 0..h {
                for cc in 0..c {
                    let from = x.index(cc, z, y0 + y, x0);
                    let source = &x.data[from..from + w];
                    let to = ((y + p) * c + cc) * row;
                    for (dst, &(from_col, to_col, offset)) in in_tiles.iter_mut().zip(&spans) {
                        if from_col < to_col {
                            copy_run(
                                &mut dst[to + offset..to + offset + to_col - from_col],
                                &source[from_col..to_col],
                            );
                        }
                    }
                }
            }
        });
        Self {
            data,
            channels: c,
            depth,
            height,
            row,
            shape,
            p,
            step,
            pairs: false,
            channel_pairs: false,
        }
    }

    /// The padded, tiled layout of a `shape` tensor whose every value the caller writes
    /// ([`write_tiles`]): the zero border is zero, the rest unspecified (a spare buffer's old
    /// values).
    fn for_writing(shape: [usize; 4], p: usize, step: usize, row: usize) -> Self {
        let [c, d, h, w] = shape;
        let (depth, height) = (d + 2 * p, h + 2 * p);
        let tiles = w.div_ceil(step).max(1);
        let layout = Layout { shape, p, step, row };
        let (mut data, dirty) = spare_buffer(tiles * c * depth * height * row, layout);
        if dirty {
            data.par_chunks_mut((height * c * row).max(1))
                .enumerate()
                .for_each(|(block, dst)| layout.zero_border(dst, block / depth.max(1), block % depth.max(1)));
        }
        Self {
            data,
            channels: c,
            depth,
            height,
            row,
            shape,
            p,
            step,
            pairs: false,
            channel_pairs: false,
        }
    }

    /// The tensor itself, its padding and halos dropped (from channel pairs, each value as its
    /// pair holds it, in bfloat16).
    fn to_tensor(&self) -> Tensor {
        let [_, d, h, w] = self.shape;
        let mut out = Tensor::zeros(self.shape);
        out.data
            .par_chunks_mut((h * w).max(1))
            .enumerate()
            .for_each(|(plane, dst)| {
                let (cc, z) = (plane / d.max(1), plane % d.max(1));
                // Channel pairs: channel `2p` in the low halves of row `2p`'s slots, `2p + 1` in
                // their high halves.
                let (row_of, high) = if self.channel_pairs {
                    (cc - cc % 2, cc % 2 == 1)
                } else {
                    (cc, false)
                };
                for y in 0..h {
                    for (t, x0) in (0..w).step_by(self.step.max(1)).enumerate() {
                        let columns = self.step.min(w - x0);
                        let at = self.tile_row_start(t, row_of, z + self.p, y + self.p) + self.p;
                        let (to, from) = (&mut dst[y * w + x0..y * w + x0 + columns], &self.data[at..at + columns]);
                        if !self.channel_pairs {
                            to.copy_from_slice(from);
                            continue;
                        }
                        for (v, slot) in to.iter_mut().zip(from) {
                            let bits = slot.to_bits();
                            *v = f32::from_bits(if high { bits & 0xffff_0000 } else { bits << 16 });
                        }
                    }
                }
            });
        out
    }

    /// Row `(c, z, y)` of the padded grid (tile 0).
    #[inline]
    fn row(&self, c: usize, z: usize, y: usize) -> &[f32] {
        self.tile_row(0, c, z, y)
    }

    /// Row `(c, z, y)` of tile `t`.
    #[inline]
    fn tile_row(&self, t: usize, c: usize, z: usize, y: usize) -> &[f32] {
        let at = self.tile_row_start(t, c, z, y);
        &self.data[at..at + self.row]
    }

    /// Where row `(c, z, y)` of tile `t` starts in `data`.
    #[inline]
    fn tile_row_start(&self, t: usize, c: usize, z: usize, y: usize) -> usize {
        (((t * self.depth + z) * self.height + y) * self.channels + c) * self.row
    }
}

impl Drop for Padded {
    /// The buffer kept as a spare for the next layer's padded tiles (see [`spare_buffer`]).
    fn drop(&mut self) {
        let data = std::mem::take(&mut self.data);
        if data.len() >= MIN_SPARE_FLOATS {
            let layout = Layout {
                shape: self.shape,
                p: self.p,
                step: self.step,
                row: self.row,
            };
            // Shifted pairs leave values in the border: its next user zeroes it.
            offer_spare(data, (!self.pairs).then_some(layout));
        }
    }
}

/// Where the values of a tensor lie in its padded tiles ([`Padded`]), for zeroing the rest.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Layout {
    /// The tensor's `[c, d, h, w]`.
    shape: [usize; 4],
    p: usize,
    step: usize,
    row: usize,
}

impl Layout {
    /// Tile `t`'s columns of the tensor, `from .. to`, and where the first lies in the tile's
    /// rows (its own columns and the halos its neighbours give it).
    fn columns(&self, t: usize) -> (usize, usize, usize) {
        let w = self.shape[3];
        // Padded columns [t·step, t·step + row) of the whole padded row, i.e. tensor columns from
        // t·step − p.
        let first = (t * self.step) as isize - self.p as isize;
        let from = first.max(0) as usize;
        let to = ((first + self.row as isize).max(0) as usize).min(w);
        (from, to, (from as isize - first).max(0) as usize)
    }

    /// Zeroes everything of the block of tile `t`'s padded plane `zz` (`[h + 2p][c][row]`) that
    /// holds no tensor value: the border planes and rows, and the columns outside
    /// [`Layout::columns`].
    fn zero_border(&self, block: &mut [f32], t: usize, zz: usize) {
        let [c, d, h, _] = self.shape;
        let (p, row) = (self.p, self.row);
        let (from, to, offset) = self.columns(t);
        let width = to.saturating_sub(from);
        if zz < p || zz >= d + p || width == 0 {
            block.fill(0.0);
            return;
        }
        for (y, rows) in block.chunks_mut((c * row).max(1)).enumerate() {
            if y < p || y >= h + p {
                rows.fill(0.0);
                continue;
            }
            for values in rows.chunks_mut(row.max(1)) {
                values[..offset.min(row)].fill(0.0);
                values[(offset + width).min(row)..].fill(0.0);
            }
        }
    }
}

thread_local! {
    /// Buffers of padded tiles that this thread's layers no longer need, kept for the next
    /// ones: a layer's padded input or output taken from here is neither zeroed whole (`calloc`
    /// of reused memory) nor faulted in afresh (memory handed back to the system between
    /// layers), only its border zeroed. At full size a layer's tensor is over 100 MB and that
    /// zeroing was a tenth of MFuseNet's time (docs/benchmarks.md). Each is kept with the layout
    /// it held (`None`: unknown), whose border is zero.
    static SPARES: std::cell::RefCell<Vec<Spare>> = const { std::cell::RefCell::new(Vec::new()) };
    /// At most this many spares on this thread ([`keep_spares`]).
    static MAX_SPARES: std::cell::Cell<usize> = const { std::cell::Cell::new(DEFAULT_SPARES) };
}

/// At most this many spares per thread by default: in inference a layer frees its input while
/// its output is alive, the next one takes it; more would only hold memory (full-size tensors
/// of over 100 MB each).
const DEFAULT_SPARES: usize = 2;

/// Lets this thread keep up to `count` spare buffers (default 2) and returns the limit before.
/// Training, whose pass keeps every layer's tensors for the backward pass and frees them all at
/// its end, reuses more of them from step to step with 8 (crops of 128 px: 1.21 → 1.14 s a step
/// of the lite five-view network, docs/experiments.md, 2026-11-29), its tensors being a few MB
/// each.
pub fn keep_spares(count: usize) -> usize {
    MAX_SPARES.with(|max| max.replace(count))
}

/// Smaller buffers (the coarse levels', tests') are left to the allocator.
const MIN_SPARE_FLOATS: usize = 1 << 18;

/// Whether a spare of `capacity` floats is taken for `len`: it holds them, and not more than twice
/// (a 4-channel buffer is not held by a 1-channel tensor, nor the coarse levels' by a tensor
/// half their size).
fn fits(capacity: usize, len: usize) -> bool {
    capacity >= len && capacity <= 2 * len
}

/// A spare buffer and the layout of the padded tiles it held (their border zero), if known.
type Spare = (Vec<f32>, Option<Layout>);

/// Keeps `data` as a spare of this thread (dropped when it has as many as [`keep_spares`] allows).
fn offer_spare(data: Vec<f32>, layout: Option<Layout>) {
    let max = MAX_SPARES.with(std::cell::Cell::get);
    SPARES.with_borrow_mut(|spares| {
        if spares.len() < max {
            spares.push((data, layout));
        }
    });
}

/// A spare of this thread for `len` floats, and whether its border must be zeroed: the one that
/// held `layout` (its border zero already: a feature tower's layers all share one), else the
/// smallest that [`fits`] (its old values left in place).
fn take_spare(len: usize, layout: Option<Layout>) -> Option<(Vec<f32>, bool)> {
    SPARES.with_borrow_mut(|spares| {
        let same = layout.and_then(|layout| {
            spares
                .iter()
                .position(|(data, held)| *held == Some(layout) && data.len() == len)
        });
        if let Some(i) = same {
            return Some((spares.swap_remove(i).0, false));
        }
        let best = (0..spares.len())
            .filter(|&i| fits(spares[i].0.capacity(), len))
            .min_by_key(|&i| spares[i].0.capacity())?;
        let mut data = spares.swap_remove(best).0;
        data.resize(len, 0.0);
        Some((data, true))
    })
}

/// A buffer of `len` floats for padded tiles laid out as `layout`, and whether its border must
/// be zeroed: a spare ([`take_spare`]), else a new zeroed one.
fn spare_buffer(len: usize, layout: Layout) -> (Vec<f32>, bool) {
    take_spare(len, Some(layout)).unwrap_or_else(|| (vec![0f32; len], false))
}

/// A buffer of `len` floats whose every value the caller writes: a spare with its old values
/// ([`take_spare`]), else a new zeroed one.
fn scratch_buffer(len: usize) -> Vec<f32> {
    take_spare(len, None).map_or_else(|| vec![0f32; len], |(data, _)| data)
}

/// Frees this thread's spare buffers (at the end of a network's pass, so that they do not hold
/// memory through what follows).
pub fn release_spares() {
    SPARES.with_borrow_mut(Vec::clear);
}

/// The arithmetic of the convolutions' products in inference.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// Inputs and weights in f32 (training always).
    #[default]
    F32,
    /// [`Precision::Bf16`] where the host's bfloat16 products are faster than its f32 ones
    /// ([`bf16_kernel::preferred`]: AMD from Zen 4); on a host with Intel's matrix unit
    /// ([`super::amx_kernel`]) for the 5³ and 7³ layers of an even number of input channels
    /// (the paper networks' Middlebury scene 2.6 → 1.8 s on a Xeon); else f32 (Intel's
    /// `vdpbf16ps` issues on one port, so its pairs make no more products per cycle than two
    /// FMAs, and the rounding costs the rest: the lite network 1.27 s in bfloat16 against
    /// 0.95 s in f32 on a Xeon with AVX512-BF16, and its 3³ layers no faster on the matrix unit,
    /// whose loads wait on every row outside L1; docs/benchmarks.md).
    Auto,
    /// Inputs and weights rounded to bfloat16, the sums in f32 ([`super::bf16_kernel`]), for the
    /// 3³, 5³ and 7³ layers where the host has AVX512-BF16; elsewhere (and for 1³ layers) f32.
    Bf16,
    /// Inputs and weights quantised to 16-bit integers, pairs of input channels multiplied and
    /// summed by `vpmaddwd` ([`super::int16_kernel`]), for the 3³, 5³ and 7³ layers of two or
    /// more input channels on AVX2; elsewhere f32.
    Int16,
}

thread_local! {
    /// The precision of the convolutions this thread starts ([`with_precision`]).
    static PRECISION: std::cell::Cell<Precision> = const { std::cell::Cell::new(Precision::F32) };
}

/// Runs `f` with the convolutions that this thread starts in `precision`, then restores the
/// precision before (also when `f` panics). Per thread, so that a test or a method in
/// bfloat16 does not change another thread's convolutions; a convolution's own worker threads
/// follow the thread that started it.
pub fn with_precision<R>(precision: Precision, f: impl FnOnce() -> R) -> R {
    struct Restore(Precision);
    impl Drop for Restore {
        fn drop(&mut self) {
            PRECISION.with(|p| p.set(self.0));
        }
    }
    let _restore = Restore(PRECISION.with(|p| p.replace(precision)));
    f()
}

/// The precision of the convolutions this thread starts.
pub fn precision() -> Precision {
    PRECISION.with(std::cell::Cell::get)
}

/// The precision a layer with kernel `k` and `cin` input channels runs in here: bfloat16 where
/// asked (or asked `Auto` on a host that prefers it), the kernel has pairs of taps to share (3,
/// 5, 7) and the host has the instructions; 16-bit integers where asked, the kernel is 3, 5 or 7
/// and there are channels to pair.
pub fn effective_precision_for(k: usize, cin: usize) -> Precision {
    let odd = k >= 3 && k % 2 == 1;
    let bf16 = odd && bf16_kernel::available();
    let int16 = odd && cin >= 2 && int16_kernel::available();
    match precision() {
        Precision::Bf16 if bf16 => Precision::Bf16,
        Precision::Auto if bf16 && bf16_kernel::preferred() => Precision::Bf16,
        // Channel pairs of the 5³ and 7³ layers on the matrix unit (a single channel's pairs of
        // taps, and the 3³ layers, stay in f32 there).
        Precision::Auto if bf16 && k >= amx_kernel::MIN_KERNEL && cin.is_multiple_of(2) && amx_kernel::available() => {
            Precision::Bf16
        }
        Precision::Int16 if int16 => Precision::Int16,
        _ => Precision::F32,
    }
}

/// [`effective_precision_for`] a layer of 4 input channels (the networks' usual width): what
/// the run's details report.
pub fn effective_precision(k: usize) -> Precision {
    effective_precision_for(k, 4)
}

#[inline]
fn load(values: &[f32]) -> f32x8 {
    let lanes: [f32; LANES] = values[..LANES].try_into().unwrap_or([0.0; LANES]);
    f32x8::from(lanes)
}

/// `out[o][z] = bias[o] + Σ_{i,t} w[o][i][t] · x[i][z − k/2 + t]` (zero outside), `weight`
/// `[cout][cin][k][k][k]` as PyTorch's Conv3d. `k` is 1, 3, 5 or 7.
pub fn conv3d_same(x: &Tensor, weight: &[f32], cout: usize, k: usize, bias: Option<&[f32]>) -> Tensor {
    conv3d_with(x, weight, cout, k, bias, Epilogue::default())
}

/// What [`conv3d_with`] does besides [`conv3d_same`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Epilogue {
    /// 1 or 2 (larger values act as 2). Keep every `stride`-th output in each dimension, from 0 (`[c, ⌈d/s⌉, ⌈h/s⌉, ⌈w/s⌉]`):
    /// 2 is the stride-2 convolution with padding `k / 2` (equal to [`Tensor::subsample2`] of the
    /// stride-1 output), computing only the planes and rows it keeps.
    pub stride: usize,
    /// `max(0, ·)` on the output (the ReLU after a folded BatchNorm).
    pub relu: bool,
}

impl Default for Epilogue {
    fn default() -> Self {
        Self { stride: 1, relu: false }
    }
}

#[inline]
fn activate(v: f32, relu: bool) -> f32 {
    if relu { v.max(0.0) } else { v }
}

/// [`conv3d_same`] with a stride and a ReLU applied as the outputs are written (inference: no
/// second pass over the tensor).
pub fn conv3d_with(
    x: &Tensor,
    weight: &[f32],
    cout: usize,
    k: usize,
    bias: Option<&[f32]>,
    epilogue: Epilogue,
) -> Tensor {
    conv_source(
        ConvInput::Borrowed(x),
        weight,
        cout,
        k,
        bias,
        epilogue,
        Output::Tensor(None),
    )
    .tensor()
}

/// [`conv3d_with`] of any [`ConvInput`]: one handed over (`Owned`) is freed once its padded copy
/// is made, before the output is allocated (inference's widest layer, `concat`, holds its 16
/// feature channels once instead of twice).
pub fn conv3d_input(
    x: ConvInput<'_>,
    weight: &[f32],
    cout: usize,
    k: usize,
    bias: Option<&[f32]>,
    epilogue: Epilogue,
) -> Tensor {
    conv_source(x, weight, cout, k, bias, epilogue, Output::Tensor(None)).tensor()
}

/// The stride-1 [`conv3d_with`] (bias, then the ReLU with `relu`) written straight into the
/// padded tiles that a convolution with kernel `next_k` reads: that layer skips its padded copy
/// of its input (a copy of the whole tensor per layer, bandwidth-bound at full size).
pub fn conv3d_padded(
    x: ConvInput<'_>,
    weight: &[f32],
    cout: usize,
    k: usize,
    bias: Option<&[f32]>,
    relu: bool,
    next_k: usize,
) -> PaddedTensor {
    padded_output(x, (weight, cout, k, bias), relu, next_k, false)
}

/// [`conv3d_padded`] (`pairs` false) and [`conv3d_padded_pairs`] (true).
fn padded_output(
    x: ConvInput<'_>,
    (weight, cout, k, bias): (&[f32], usize, usize, Option<&[f32]>),
    relu: bool,
    next_k: usize,
    pairs: bool,
) -> PaddedTensor {
    let epilogue = Epilogue { stride: 1, relu };
    match conv_source(x, weight, cout, k, bias, epilogue, Output::Padded(next_k, pairs)) {
        Written::Padded(p) => PaddedTensor(p),
        Written::Tensor(t) => PaddedTensor::of(&t, next_k),
    }
}

/// [`conv3d_padded`] for a convolution that pairs channels in bfloat16 (this thread's precision
/// bfloat16, the host with AVX512-BF16, an even `cout`): the padded tiles are written as its
/// channel pairs, so that it skips rewriting them (a pass over its whole input) and the odd
/// channels' rows are never written. Elsewhere the same as [`conv3d_padded`]. Only for a
/// convolution's input: [`PaddedTensor::combine`] refuses channel pairs, and
/// [`PaddedTensor::to_tensor`] reads them back in bfloat16.
pub fn conv3d_padded_pairs(
    x: ConvInput<'_>,
    weight: &[f32],
    cout: usize,
    k: usize,
    bias: Option<&[f32]>,
    relu: bool,
    next_k: usize,
) -> PaddedTensor {
    padded_output(x, (weight, cout, k, bias), relu, next_k, true)
}

/// The kernel `weight` (`[cout][cin][k³]`) restricted to the input channels `channels`:
/// `[cout][channels.len()][k³]`, for [`conv3d_accumulate_input`] over a group of channels.
pub fn input_channels(weight: &[f32], cout: usize, cin: usize, k: usize, channels: Range<usize>) -> Vec<f32> {
    let taps = k * k * k;
    (0..cout)
        .flat_map(|o| {
            weight[(o * cin + channels.start) * taps..(o * cin + channels.end) * taps]
                .iter()
                .copied()
        })
        .collect()
}

/// `into += conv3d_same(x, weight, cout, k, None)`, then `max(0, ·)` with `relu`; `x` (if
/// handed over) freed once padded: a convolution over many input channels computed a group of
/// channels at a time (each group's input made, added in and freed), so that the whole input
/// never exists. `into` must have the output's shape (else a new tensor is written).
pub fn conv3d_accumulate_input(x: ConvInput<'_>, weight: &[f32], k: usize, into: Tensor, relu: bool) -> Tensor {
    let cout = into.shape[0];
    let epilogue = Epilogue { stride: 1, relu };
    conv_source(x, weight, cout, k, None, epilogue, Output::Tensor(Some(into))).tensor()
}

/// A convolution's input, lent or handed over; or the output of a convolution written straight
/// into the padded tiles a convolution with kernel `k` reads ([`conv3d_padded`]), which that
/// convolution reads without copying.
pub enum ConvInput<'a> {
    /// A tensor the caller keeps.
    Borrowed(&'a Tensor),
    /// A tensor freed once its padded copy is made.
    Owned(Tensor),
    /// Padded tiles, read as they are when made for this kernel size (else copied).
    Padded(PaddedTensor),
    /// The `rows × columns` window of a tensor the caller keeps, read as if cropped (the
    /// window's padded copy is the only copy).
    Window(&'a Tensor, Range<usize>, Range<usize>),
}

/// A tensor held as a convolution reads it: zero-padded and cut into column tiles with their
/// halos (made by [`conv3d_padded`] for the next layer's kernel size).
pub struct PaddedTensor(Padded);

impl PaddedTensor {
    /// `x` padded and tiled for a convolution with kernel `k`.
    pub fn of(x: &Tensor, k: usize) -> Self {
        let p = k / 2;
        PaddedTensor(Padded::tiled(x, p, TILE_BLOCKS * BLOCK, TILE_BLOCKS * BLOCK + 2 * p))
    }

    /// `[c, d, h, w]` of the tensor it holds.
    pub fn shape(&self) -> [usize; 4] {
        self.0.shape
    }

    /// The tensor it holds.
    pub fn to_tensor(&self) -> Tensor {
        self.0.to_tensor()
    }

    /// Whether `other` lies in the same padded tiles (shape, border, tile step and row): then
    /// value-by-value operations on the two buffers are operations on the tensors, the zero
    /// border staying zero under a sum, a maximum and a scaling.
    pub fn same_layout(&self, other: &Self) -> bool {
        let (a, b) = (&self.0, &other.0);
        (a.shape, a.p, a.step, a.row, a.data.len()) == (b.shape, b.p, b.step, b.row, b.data.len())
            && !a.channel_pairs
            && !b.channel_pairs
    }

    /// A copy in the same layout (a spare buffer when one is kept).
    pub fn duplicate(&self) -> Self {
        let layout = Layout {
            shape: self.0.shape,
            p: self.0.p,
            step: self.0.step,
            row: self.0.row,
        };
        let (mut data, _) = spare_buffer(self.0.data.len(), layout);
        data.par_chunks_mut(PARALLEL_CHUNK)
            .zip(self.0.data.par_chunks(PARALLEL_CHUNK))
            .for_each(|(to, from)| to.copy_from_slice(from));
        let a = &self.0;
        PaddedTensor(Padded {
            data,
            channels: a.channels,
            depth: a.depth,
            height: a.height,
            row: a.row,
            shape: a.shape,
            p: a.p,
            step: a.step,
            pairs: a.pairs,
            channel_pairs: a.channel_pairs,
        })
    }

    /// Every value replaced by `op(value, other's value)`; `false` (and nothing changed) when
    /// `other` is not in the same layout ([`PaddedTensor::same_layout`]).
    pub fn combine(&mut self, other: &Self, op: impl Fn(f32, f32) -> f32 + Sync) -> bool {
        if !self.same_layout(other) {
            return false;
        }
        self.0
            .data
            .par_chunks_mut(PARALLEL_CHUNK)
            .zip(other.0.data.par_chunks(PARALLEL_CHUNK))
            .for_each(|(to, from)| to.iter_mut().zip(from).for_each(|(t, f)| *t = op(*t, *f)));
        true
    }

    /// Every value multiplied by `factor`.
    pub fn scale(&mut self, factor: f32) {
        self.0
            .data
            .par_chunks_mut(PARALLEL_CHUNK)
            .for_each(|chunk| chunk.iter_mut().for_each(|v| *v *= factor));
    }
}

/// How many output rows ahead a convolution asks for the input rows it will read
/// ([`fma_kernel::prefetch_last_rows`]; 0, 2 and 3 measured: 2 and 3 alike, 0 a little slower).
const PREFETCH_ROWS_AHEAD: usize = 2;

/// Values per task of the padded tensors' value-by-value operations (256 KB).
const PARALLEL_CHUNK: usize = 1 << 16;

impl ConvInput<'_> {
    fn shape(&self) -> [usize; 4] {
        match self {
            ConvInput::Borrowed(x) => x.shape,
            ConvInput::Owned(x) => x.shape,
            ConvInput::Padded(x) => x.0.shape,
            ConvInput::Window(x, rows, columns) => {
                let [c, d, h, w] = x.shape;
                let span = |r: &Range<usize>, n: usize| r.end.min(n).saturating_sub(r.start.min(n));
                [c, d, span(rows, h), span(columns, w)]
            }
        }
    }

    /// The padded tiles a kernel of size `2p + 1` reads: the input's own when they are laid out
    /// so, else a padded copy (the input freed once copied when it was handed over).
    fn into_padded(self, p: usize, step: usize, row: usize) -> Padded {
        match self {
            ConvInput::Borrowed(x) => Padded::tiled(x, p, step, row),
            ConvInput::Owned(x) => Padded::tiled(&x, p, step, row),
            ConvInput::Padded(x) if x.0.p == p && x.0.step == step && x.0.row == row => x.0,
            ConvInput::Padded(x) => Padded::tiled(&x.0.to_tensor(), p, step, row),
            ConvInput::Window(x, rows, columns) => Padded::tiled_window(x, (rows, columns), p, step, row),
        }
    }
}

/// What a convolution writes.
enum Output {
    /// A new tensor, or the sum into `into` where it has the output's shape.
    Tensor(Option<Tensor>),
    /// The padded tiles of a convolution with this kernel size (stride 1 only); with `true`, as
    /// bfloat16 channel pairs where that convolution pairs channels.
    Padded(usize, bool),
}

/// What a convolution wrote.
enum Written {
    Tensor(Tensor),
    Padded(Padded),
}

impl Written {
    fn tensor(self) -> Tensor {
        match self {
            Written::Tensor(t) => t,
            Written::Padded(p) => p.to_tensor(),
        }
    }
}

/// The convolution of `x`, written into a new tensor, added into one, or written as padded tiles.
fn conv_source(
    x: ConvInput<'_>,
    weight: &[f32],
    cout: usize,
    k: usize,
    bias: Option<&[f32]>,
    epilogue: Epilogue,
    output: Output,
) -> Written {
    match k {
        1 => conv_k::<1>(x, weight, cout, bias, epilogue, output),
        3 => conv_k::<3>(x, weight, cout, bias, epilogue, output),
        5 => conv_k::<5>(x, weight, cout, bias, epilogue, output),
        _ => conv_k::<7>(x, weight, cout, bias, epilogue, output),
    }
}

/// Where one job (channel group, output plane) writes: its planes of a tensor (`[o]`), or its
/// padded plane of each tile of a padded output (`[tile]`, every channel: one group).
enum Destination<'a> {
    Planes(Vec<&'a mut [f32]>),
    Tiles(Vec<&'a mut [f32]>),
}

/// Where [`write_tiles`] writes in a tile's padded plane: the border `p`, `step` columns per tile,
/// `channels` rows `row` long per padded row.
#[derive(Debug, Clone, Copy)]
struct TilePlane {
    p: usize,
    step: usize,
    channels: usize,
    row: usize,
}

/// Output row `y`'s columns `x0 ..` (`values`) of channel `o` and one plane into the padded tiles
/// (each tile's padded plane in `tiles`): at their place in their tile, and the `p` columns at
/// either edge of a tile into the neighbour tile's halo as well.
fn write_tiles(tiles: &mut [&mut [f32]], o: usize, values: &[f32], x0: usize, y: usize, plane: TilePlane) {
    let TilePlane { p, step, channels, row } = plane;
    let t = x0 / step;
    let at = ((y + p) * channels + o) * row;
    let start = x0 % step;
    if let Some(tile) = tiles.get_mut(t) {
        copy_short(&mut tile[at + start + p..at + start + p + values.len()], values);
    }
    let end = start + values.len();
    // The columns within `p` of the tile's left edge are the previous tile's right halo too …
    let to = p.min(end);
    if t > 0
        && start < to
        && let Some(previous) = tiles.get_mut(t - 1)
    {
        copy_short(
            &mut previous[at + step + p + start..at + step + p + to],
            &values[..to - start],
        );
    }
    // … and those within `p` of its right edge the next tile's left halo.
    let from = step.saturating_sub(p).max(start);
    if from < end
        && let Some(next) = tiles.get_mut(t + 1)
    {
        copy_short(
            &mut next[at + from + p - step..at + end + p - step],
            &values[from - start..end - start],
        );
    }
}

/// `dst.copy_from_slice(src)` for the short runs [`write_tiles`] copies (a block, or a halo of a
/// few columns), inlined: as `copy_from_slice` of a run-time length each was a call into libc's
/// `memcpy`, about a tenth of MFuseNet's time at 640×360.
#[inline(always)]
fn copy_short(dst: &mut [f32], src: &[f32]) {
    if let (Ok(d), Ok(s)) = (<&mut [f32; BLOCK]>::try_from(&mut *dst), <&[f32; BLOCK]>::try_from(src)) {
        *d = *s;
        return;
    }
    let mut chunks = dst.chunks_exact_mut(4).zip(src.chunks_exact(4));
    for (d, s) in &mut chunks {
        if let (Ok(d), Ok(s)) = (<&mut [f32; 4]>::try_from(d), <&[f32; 4]>::try_from(s)) {
            *d = *s;
        }
    }
    let n = dst.len().min(src.len());
    let whole = n / 4 * 4;
    // At most three values left: one at a time (a loop here would become a `memcpy` call again).
    match (&mut dst[whole..n], &src[whole..n]) {
        ([a], [x]) => *a = *x,
        ([a, b], [x, y]) => (*a, *b) = (*x, *y),
        ([a, b, c], [x, y, z]) => (*a, *b, *c) = (*x, *y, *z),
        _ => {}
    }
}

/// `dst.copy_from_slice(src)` for a tile's row of an input (a few dozen floats), inlined: 16
/// floats at a time, then [`copy_short`]. As `copy_from_slice` each row was a call into libc's
/// `memcpy`, about 6 % of MFuseNet's time on the demo's capture.
#[inline(always)]
fn copy_run(dst: &mut [f32], src: &[f32]) {
    let n = dst.len().min(src.len());
    let whole = n / 16 * 16;
    for (d, s) in dst[..whole].chunks_exact_mut(16).zip(src[..whole].chunks_exact(16)) {
        if let (Ok(d), Ok(s)) = (<&mut [f32; 16]>::try_from(d), <&[f32; 16]>::try_from(s)) {
            *d = *s;
        }
    }
    copy_short(&mut dst[whole..n], &src[whole..n]);
}

fn conv_k<const K: usize>(
    source: ConvInput<'_>,
    weight: &[f32],
    cout: usize,
    bias: Option<&[f32]>,
    epilogue: Epilogue,
    output: Output,
) -> Written {
    let [cin, d, h, w] = source.shape();
    // 1 or 2 (blocks start at multiples of 24 columns, so even columns stay even).
    let stride = epilogue.stride.clamp(1, 2);
    let (od, oh, ow) = (d.div_ceil(stride), h.div_ceil(stride), w.div_ceil(stride));
    let relu = epilogue.relu;
    let p = K / 2;
    let blocks = w.div_ceil(BLOCK);
    let step = TILE_BLOCKS * BLOCK;
    // Only the padded tiles are read from here on (a handed-over input freed once copied).
    let mut padded = source.into_padded(p, step, step + K - 1);
    // In bfloat16, the padded tiles become shifted pairs in place (same size) and every tile,
    // a partial last one included, goes through the bfloat16 kernel.
    let precision = effective_precision_for(K, cin);
    let bf16 = precision == Precision::Bf16;
    // An even number of input channels pairs channels (no product wasted), an odd one (the
    // first layers' single volume) taps along the row.
    // (Channel pairs against pairs of taps, the same layers in bfloat16: 3³ 4 → 4 and 16 → 4 and
    // 7³ 8 → 4 about 13 % faster, `cargo bench -p fuse --bench methods -- bf16`.)
    let bf16_channels = bf16 && cin.is_multiple_of(2);
    if padded.channel_pairs && !bf16_channels {
        // (Written for a layer that pairs channels, read by one that does not: values again.)
        padded = Padded::tiled(&padded.to_tensor(), p, step, step + K - 1);
    }
    if bf16_channels {
        if !padded.channel_pairs {
            bf16_kernel::to_channel_pairs(&mut padded.data, cin, padded.row);
        }
        padded.pairs = true;
    } else if bf16 {
        bf16_kernel::to_shifted_pairs(&mut padded.data);
        padded.pairs = true;
    }
    // In 16-bit integers, the padded tiles become quantised channel pairs in place, at the scale
    // of this input's largest value.
    let int16 = precision == Precision::Int16;
    let input_scale = if int16 {
        let scale = int16_kernel::input_scale(int16_kernel::max_abs(&padded.data));
        int16_kernel::to_channel_pairs(&mut padded.data, cin, padded.row, scale);
        padded.pairs = true;
        scale
    } else {
        1.0
    };
    let groups = cout.div_ceil(GROUP);
    // Weights per group as [i][td][th][tw][4] (missing channels zero).
    let taps = K * K * K;
    let mut packed = vec![0f32; groups * cin * taps * GROUP];
    for o in 0..cout {
        for i in 0..cin {
            for t in 0..taps {
                packed[((o / GROUP * cin + i) * taps + t) * GROUP + o % GROUP] = weight[(o * cin + i) * taps + t];
            }
        }
    }
    // The same weights as bfloat16 pairs of taps, `[g][i][td][th][pair][4]`.
    let pair_weights = if bf16_channels {
        (0..groups)
            .flat_map(|g| {
                bf16_kernel::pack_channel_weights::<K>(
                    &packed[g * cin * taps * GROUP..(g + 1) * cin * taps * GROUP],
                    cin,
                )
            })
            .collect()
    } else if bf16 {
        bf16_kernel::pack_weights::<K>(&packed)
    } else {
        Vec::new()
    };
    let pair_weights_per_group = if bf16_channels {
        cin.div_ceil(2) * taps * GROUP
    } else {
        cin * K * K * bf16_kernel::pairs_per_row(K) * GROUP
    };
    // The channel pairs' weights as the matrix unit's tiles, one per input row, where it runs.
    let amx = bf16_channels && amx_kernel::available();
    let amx_tiles_per_group = cin.div_ceil(2) * K * K * amx_kernel::tile_len(K);
    let amx_tiles: Vec<f32> = if amx {
        pair_weights
            .chunks_exact(pair_weights_per_group.max(1))
            .flat_map(|group| amx_kernel::pack_weights::<K>(group, cin.div_ceil(2) * K * K))
            .collect()
    } else {
        Vec::new()
    };
    // Per group, the weights as quantised pairs of input channels, and the table of each pair's
    // `K²` rows (the even channel's rows, which hold the pairs).
    let int16_weights: Vec<int16_kernel::PairWeights> = if int16 {
        (0..groups)
            .map(|g| {
                int16_kernel::pack_weights::<K>(
                    &packed[g * cin * taps * GROUP..(g + 1) * cin * taps * GROUP],
                    cin,
                    input_scale,
                )
            })
            .collect()
    } else {
        Vec::new()
    };
    let pair_rows = fma_kernel::RowTable::new(if int16 || bf16_channels {
        (0..cin.div_ceil(2))
            .flat_map(|p| (0..K).flat_map(move |td| (0..K).map(move |th| (p, td, th))))
            .map(|(p, td, th)| padded.tile_row_start(0, 2 * p, td, th))
            .collect()
    } else {
        Vec::new()
    });
    // Each input row (i, td, th) a block reads, as an offset from row (0, z, y) of its tile, in
    // the packed weights' order (for the assembly kernels, `fma_kernel`).
    let rows = fma_kernel::RowTable::new(
        (0..cin)
            .flat_map(|i| (0..K).flat_map(move |td| (0..K).map(move |th| (i, td, th))))
            .map(|(i, td, th)| padded.tile_row_start(0, i, td, th))
            .collect(),
    );
    // The input is cut into column tiles of TILE_BLOCKS blocks, each tile's rows short and
    // contiguous: an output row's block reads cin · K² input rows (392 at k7 with 8 channels),
    // and whole-width rows (1.75 KB apart at 428 columns) spread them over as many pages and ran
    // at half the speed (81 against 137 GFLOP/s on 2 AMD EPYC vCPUs).
    let tiles = blocks.div_ceil(TILE_BLOCKS);
    let wide = wide_kernel::available();
    let plane = oh * ow;
    let pairs_wanted = matches!(output, Output::Padded(_, true));
    let (into, padded_for) = match output {
        Output::Tensor(into) => (into, None),
        // Padded output at stride 1 and of one channel group only (a strided layer's output, or
        // a wider one, is a tensor, padded by its reader).
        Output::Padded(next_k, _) if stride == 1 && groups == 1 => (None, Some(next_k)),
        Output::Padded(..) => (None, None),
    };
    // Channel pairs for the next layer where it pairs channels (the rule of its own choice).
    let pairs_out = pairs_wanted
        && cout.is_multiple_of(2)
        && padded_for.is_some_and(|next_k| effective_precision_for(next_k, cout) == Precision::Bf16);
    // Added into `into` when it has the output's shape (stride 1).
    let accumulate = stride == 1 && into.as_ref().is_some_and(|t| t.shape == [cout, od, oh, ow]);
    let mut written = match padded_for {
        Some(next_k) => {
            let np = next_k / 2;
            let mut padded = Padded::for_writing([cout, od, oh, ow], np, step, step + 2 * np);
            padded.pairs = pairs_out;
            padded.channel_pairs = pairs_out;
            Written::Padded(padded)
        }
        // A new tensor is written whole: a spare buffer's old values need no zeroing.
        None => Written::Tensor(into.filter(|_| accumulate).unwrap_or_else(|| Tensor {
            shape: [cout, od, oh, ow],
            data: scratch_buffer(cout * od * oh * ow),
        })),
    };
    let tile_plane = match &written {
        Written::Padded(out) => TilePlane {
            p: out.p,
            step,
            channels: cout,
            row: out.row,
        },
        Written::Tensor(_) => TilePlane {
            p: 0,
            step,
            channels: cout,
            row: 0,
        },
    };
    // One job per (channel group, output plane), writing its output planes in place: the planes
    // of the tensor ([c][z]) regrouped as [g][z][o], or the padded planes of the tiles ([t][z'])
    // as [z][t] (one group).
    let channel_range = |g: usize| g * GROUP..((g + 1) * GROUP).min(cout);
    let keys: Vec<(usize, usize)> = (0..groups).flat_map(|g| (0..od).map(move |z| (g, z))).collect();
    let destinations: Vec<Destination<'_>> = match &mut written {
        Written::Tensor(out) => {
            let mut planes: Vec<Option<&mut [f32]>> = out.data.chunks_mut(plane.max(1)).map(Some).collect();
            keys.iter()
                .map(|&(g, z)| {
                    Destination::Planes(
                        channel_range(g)
                            .filter_map(|channel| planes.get_mut(channel * od + z).and_then(Option::take))
                            .collect(),
                    )
                })
                .collect()
        }
        Written::Padded(out) => {
            let (np, depth, chunk) = (out.p, out.depth, (out.height * out.channels * out.row).max(1));
            let mut chunks: Vec<Option<&mut [f32]>> = out.data.chunks_mut(chunk).map(Some).collect();
            let tiles_out = w.div_ceil(step).max(1);
            keys.iter()
                .map(|&(_, z)| {
                    Destination::Tiles(
                        (0..tiles_out)
                            .filter_map(|t| chunks.get_mut(t * depth + z + np).and_then(Option::take))
                            .collect(),
                    )
                })
                .collect()
        }
    };
    let jobs: Vec<(usize, usize, Destination<'_>)> = keys
        .iter()
        .zip(destinations)
        .map(|(&(g, z), dst)| (g, z * stride, dst))
        .collect();
    jobs.into_par_iter().for_each(|(g, z, mut dst)| {
        let weights = &packed[g * cin * taps * GROUP..(g + 1) * cin * taps * GROUP];
        // A whole tile's sums on 512-bit vectors, `[o][column]`, every value written by each
        // call (no zeroing or copying per row).
        let mut pair = [0f32; GROUP * TILE_BLOCKS * BLOCK];
        // On the matrix unit, four output rows' sums at once ([`amx_kernel::ROWS_AT_ONCE`]):
        // the rows `ahead_from + i · stride`, handed out one by one.
        let mut ahead = [[0f32; GROUP * TILE_BLOCKS * BLOCK]; amx_kernel::ROWS_AT_ONCE];
        let mut ahead_from = None;
        for t in 0..tiles {
            let c0 = t * TILE_BLOCKS * BLOCK;
            let tile_blocks = t * TILE_BLOCKS..((t + 1) * TILE_BLOCKS).min(blocks);
            for y in (0..h).step_by(stride) {
                // A whole tile's two blocks at once on 512-bit vectors, where the host has them;
                // in bfloat16 every tile (a partial one's columns past the tensor are computed and
                // dropped), the portable loop over the pairs where the kernel declines.
                let base = padded.tile_row_start(t, 0, z, y);
                // The input rows an output row `PREFETCH_ROWS_AHEAD` rows on reads first, asked
                // for now.
                fma_kernel::prefetch_last_rows::<K>(
                    &padded.data,
                    base + PREFETCH_ROWS_AHEAD * stride * padded.channels * padded.row,
                    if bf16_channels || int16 { &pair_rows } else { &rows },
                    padded.row,
                );
                let paired = if bf16_channels {
                    let pair_weights = &pair_weights[g * pair_weights_per_group..(g + 1) * pair_weights_per_group];
                    let ahead_at = |from: usize| (y - from) / stride;
                    let in_ahead = ahead_from.is_some_and(|(tile, from)| {
                        tile == t && y >= from && ahead_at(from) < amx_kernel::ROWS_AT_ONCE
                    });
                    let on_tiles = amx
                        && (in_ahead || {
                            // This row and the next three (the last repeated past the plane).
                            let bases = std::array::from_fn(|i| {
                                let row = (y + i * stride).min((h - 1) / stride * stride);
                                padded.tile_row_start(t, 0, z, row)
                            });
                            let tiles_g = amx_tiles
                                .get(g * amx_tiles_per_group..(g + 1) * amx_tiles_per_group)
                                .unwrap_or(&[]);
                            let done =
                                amx_kernel::channel_rows::<K>(&padded.data, bases, &pair_rows, tiles_g, &mut ahead);
                            ahead_from = done.then_some((t, y));
                            done
                        });
                    if on_tiles && let Some((_, from)) = ahead_from {
                        pair = ahead[ahead_at(from)];
                    }
                    if !on_tiles
                        && !bf16_kernel::channel_rows::<K>(&padded.data, base, &pair_rows, pair_weights, &mut pair)
                    {
                        bf16_kernel::channel_rows_portable::<K>(
                            &padded.data,
                            base,
                            &pair_rows,
                            pair_weights,
                            &mut pair,
                        );
                    }
                    true
                } else if bf16 {
                    let pair_weights = &pair_weights[g * pair_weights_per_group..(g + 1) * pair_weights_per_group];
                    if !bf16_kernel::rows::<K>(&padded.data, base, &rows, pair_weights, &mut pair) {
                        bf16_kernel::rows_portable::<K>(&padded.data, base, &rows, pair_weights, &mut pair);
                    }
                    true
                } else if int16 {
                    let weights = &int16_weights[g];
                    if !int16_kernel::rows::<K>(&padded.data, base, &pair_rows, weights, &mut pair) {
                        int16_kernel::rows_portable::<K>(&padded.data, base, &pair_rows, weights, &mut pair);
                    }
                    true
                } else {
                    wide && tile_blocks.len() == TILE_BLOCKS
                        && wide_kernel::rows::<K>(&padded.data, base, &rows, weights, &mut pair)
                };
                if paired {
                    // The whole tile's row at once, straight from the wide sums: bias, ReLU (and the
                    // tensor's value where accumulating) in place, then one write per channel
                    // (against two blocks, each reloaded into registers and copied twice).
                    let columns = (TILE_BLOCKS * BLOCK).min(w - c0);
                    let add_of = |o: usize| bias.map_or(0.0, |bias| bias[g * GROUP + o]);
                    match &mut dst {
                        Destination::Tiles(tiles) if pairs_out => {
                            // Channels 2q and 2q + 1 as one row of bfloat16 pairs, in row 2q.
                            let width = TILE_BLOCKS * BLOCK;
                            for o in 0..cout.min(GROUP) {
                                finish_row(&mut pair[o * width..(o + 1) * width], None, add_of(o), relu);
                            }
                            for o in (0..cout.min(GROUP)).step_by(2) {
                                let (low, high) = pair[o * width..(o + 2) * width].split_at_mut(width);
                                bf16_kernel::pair_rows_into(low, high);
                                write_tiles(tiles, o, &low[..columns], c0, y, tile_plane);
                            }
                        }
                        Destination::Tiles(tiles) => {
                            for o in 0..cout.min(GROUP) {
                                let row = &mut pair[o * TILE_BLOCKS * BLOCK..(o + 1) * TILE_BLOCKS * BLOCK];
                                finish_row(row, None, add_of(o), relu);
                                write_tiles(tiles, o, &row[..columns], c0, y, tile_plane);
                            }
                        }
                        Destination::Planes(planes) => {
                            for (o, plane_o) in planes.iter_mut().enumerate() {
                                let add = add_of(o);
                                let row = &mut pair[o * TILE_BLOCKS * BLOCK..(o + 1) * TILE_BLOCKS * BLOCK];
                                let out = &mut plane_o[y / stride * ow..(y / stride + 1) * ow];
                                if stride == 1 {
                                    let out = &mut out[c0..c0 + columns];
                                    // Whole blocks as the blocks' vector epilogue computes them
                                    // (sum + bias + prior), a partial last one as its scalar loop
                                    // does (prior + sum + bias).
                                    let whole = columns / BLOCK * BLOCK;
                                    let (row_whole, row_rest) = row.split_at_mut(whole);
                                    let (out_whole, out_rest) = out.split_at_mut(whole);
                                    finish_row_into(out_whole, row_whole, accumulate, add, relu);
                                    for (v, sum) in out_rest.iter_mut().zip(row_rest.iter()) {
                                        *v = activate(if accumulate { *v + sum + add } else { sum + add }, relu);
                                    }
                                } else {
                                    // c0 is a multiple of the stride (the tile is, for the strides 1 and 2).
                                    for c in (0..columns).step_by(stride) {
                                        out[(c0 + c) / stride] = activate(row[c] + add, relu);
                                    }
                                }
                            }
                        }
                    }
                    continue;
                }
                for b in tile_blocks.clone() {
                    let x0 = b * BLOCK;
                    let mut acc = [[f32x8::ZERO; VECTORS]; GROUP];
                    let base = padded.tile_row_start(t, 0, z, y) + x0 - c0;
                    let mut flat = [0f32; ACCUMULATORS];
                    if (K == 3 || K == 5) && fma_kernel::rows::<K>(&padded.data, base, &rows, weights, &mut flat) {
                        for (o, acc_o) in acc.iter_mut().enumerate() {
                            for (j, a) in acc_o.iter_mut().enumerate() {
                                *a = load(&flat[(o * VECTORS + j) * LANES..]);
                            }
                        }
                    } else {
                        portable_block::<K>(&padded, (t, z, y), x0 - c0, cin, weights, &mut acc);
                    }
                    let columns = BLOCK.min(w - x0);
                    match &mut dst {
                        Destination::Tiles(tiles) => {
                            let mut values = [[0f32; BLOCK]; GROUP];
                            for (o, (acc_o, values_o)) in acc.iter().zip(&mut values).enumerate().take(cout) {
                                let add = bias.map_or(0.0, |bias| bias[o]);
                                for (v, lanes) in values_o.chunks_exact_mut(LANES).zip(acc_o) {
                                    let mut value = *lanes + f32x8::splat(add);
                                    if relu {
                                        value = value.max(f32x8::ZERO);
                                    }
                                    v.copy_from_slice(&value.to_array());
                                }
                            }
                            if pairs_out {
                                // Channels 2q and 2q + 1 as one row of bfloat16 pairs, in row 2q,
                                // as the whole tiles write them for a layer that pairs channels.
                                for o in (0..cout.min(GROUP)).step_by(2) {
                                    let (low, high) = values[o..o + 2].split_at_mut(1);
                                    bf16_kernel::pair_rows_into(&mut low[0], &high[0]);
                                    write_tiles(tiles, o, &low[0][..columns], x0, y, tile_plane);
                                }
                            } else {
                                for (o, values_o) in values.iter().enumerate().take(cout) {
                                    write_tiles(tiles, o, &values_o[..columns], x0, y, tile_plane);
                                }
                            }
                        }
                        Destination::Planes(planes) => {
                            for (o, (acc_o, plane_o)) in acc.iter().zip(planes.iter_mut()).enumerate() {
                                let add = bias.map_or(0.0, |bias| bias[g * GROUP + o]);
                                let row = &mut plane_o[y / stride * ow..(y / stride + 1) * ow];
                                if stride == 1 && columns == BLOCK {
                                    // A whole block: its vectors written as they are.
                                    for (v, out) in acc_o.iter().zip(row[x0..x0 + BLOCK].chunks_exact_mut(LANES)) {
                                        let mut value = *v + f32x8::splat(add);
                                        if accumulate {
                                            value += load(out);
                                        }
                                        if relu {
                                            value = value.max(f32x8::ZERO);
                                        }
                                        out.copy_from_slice(&value.to_array());
                                    }
                                    continue;
                                }
                                let lanes: [[f32; LANES]; VECTORS] = acc_o.map(|v| v.to_array());
                                if accumulate {
                                    for (c, v) in row[x0..x0 + columns].iter_mut().enumerate() {
                                        *v = activate(*v + lanes[c / LANES][c % LANES] + add, relu);
                                    }
                                } else if stride == 1 {
                                    for (c, v) in row[x0..x0 + columns].iter_mut().enumerate() {
                                        *v = activate(lanes[c / LANES][c % LANES] + add, relu);
                                    }
                                } else {
                                    // x0 is a multiple of the stride (BLOCK is, for the strides 1 and 2).
                                    for c in (0..columns).step_by(stride) {
                                        row[(x0 + c) / stride] = activate(lanes[c / LANES][c % LANES] + add, relu);
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
    });
    written
}

/// A row of sums made outputs in place, 8 lanes at a time (the arithmetic of the blocks'
/// epilogue, lane for lane): `sum + add`, plus `prior`'s value where accumulating, then the
/// ReLU. `row` holds a multiple of 8 values.
#[inline(always)]
fn finish_row(row: &mut [f32], prior: Option<&[f32]>, add: f32, relu: bool) {
    let add = f32x8::splat(add);
    for (i, chunk) in row.chunks_exact_mut(LANES).enumerate() {
        let mut value = load(chunk) + add;
        if let Some(prior) = prior {
            value += load(&prior[i * LANES..]);
        }
        if relu {
            value = value.max(f32x8::ZERO);
        }
        chunk.copy_from_slice(&value.to_array());
    }
}

/// [`finish_row`] of `row` written into `out` in the same pass (`out`'s own values the prior
/// with `accumulate`): the same values, without a copy of the row afterwards.
fn finish_row_into(out: &mut [f32], row: &[f32], accumulate: bool, add: f32, relu: bool) {
    let add = f32x8::splat(add);
    for (o, r) in out.chunks_exact_mut(LANES).zip(row.chunks_exact(LANES)) {
        let mut value = load(r) + add;
        if accumulate {
            value += load(o);
        }
        if relu {
            value = value.max(f32x8::ZERO);
        }
        o.copy_from_slice(&value.to_array());
    }
}

/// One output block's sums by the portable loop: every input row (i, td, th) of tile `t` at
/// output plane `z` and row `y`, from column `x` of the tile, `K` taps × 4 channels each.
#[inline(always)]
fn portable_block<const K: usize>(
    padded: &Padded,
    (t, z, y): (usize, usize, usize),
    x: usize,
    cin: usize,
    weights: &[f32],
    acc: &mut [[f32x8; VECTORS]; GROUP],
) {
    for i in 0..cin {
        for td in 0..K {
            for th in 0..K {
                let row = &padded.tile_row(t, i, z + td, y + th)[x..x + BLOCK + K - 1];
                let tap = ((i * K + td) * K + th) * K * GROUP;
                let wk = &weights[tap..tap + K * GROUP];
                for tw in 0..K {
                    let xs: [f32x8; VECTORS] = std::array::from_fn(|j| load(&row[tw + LANES * j..]));
                    for (o, acc_o) in acc.iter_mut().enumerate() {
                        let wv = f32x8::splat(wk[tw * GROUP + o]);
                        for (a, xv) in acc_o.iter_mut().zip(&xs) {
                            *a = xv.mul_add(wv, *a);
                        }
                    }
                }
            }
        }
    }
}

/// The kernel of the input gradient: `[cin][cout][k³]` with every tap flipped, so that the
/// gradient of a "same" convolution is itself a "same" convolution.
pub fn flip_transpose(weight: &[f32], cout: usize, cin: usize, k: usize) -> Vec<f32> {
    let taps = k * k * k;
    let mut out = vec![0f32; weight.len()];
    for o in 0..cout {
        for i in 0..cin {
            for t in 0..taps {
                out[(i * cout + o) * taps + taps - 1 - t] = weight[(o * cin + i) * taps + t];
            }
        }
    }
    out
}

/// Gradient of the input of [`conv3d_same`] (`cin` channels) given the output gradient.
pub fn conv3d_same_input_grad(grad: &Tensor, weight: &[f32], cin: usize, k: usize) -> Tensor {
    let cout = grad.shape[0];
    conv3d_same(grad, &flip_transpose(weight, cout, cin, k), cin, k, None)
}

/// Kernel taps handled together by the weight gradient (4 channels × 3 taps accumulators).
const TAP_RUN: usize = 3;

/// Gradient of the weights of [`conv3d_same`]: `dw[o][i][t] = Σ_z grad[o][z] · x[i][z − k/2 + t]`
/// (`[cout][cin][k][k][k]`), accumulated per row in vectors and across rows in `f64`.
pub fn conv3d_same_weight_grad(x: &Tensor, grad: &Tensor, k: usize) -> Vec<f32> {
    match k {
        1 => weight_grad_k::<1>(x, grad),
        3 => weight_grad_k::<3>(x, grad),
        5 => weight_grad_k::<5>(x, grad),
        _ => weight_grad_k::<7>(x, grad),
    }
}

fn weight_grad_k<const K: usize>(x: &Tensor, grad: &Tensor) -> Vec<f32> {
    let [cin, d, h, w] = x.shape;
    let cout = grad.shape[0];
    let p = K / 2;
    let row = w.div_ceil(LANES) * LANES;
    let xs = Padded::new(x, p, row + K - 1);
    let gs = Padded::new(grad, 0, row);
    let groups = cout.div_ceil(GROUP);
    let taps = K * K * K;
    let len = groups * GROUP * cin * taps;
    let sums = (0..d)
        .into_par_iter()
        .fold(
            || vec![0f64; len],
            |mut acc, z| {
                for y in 0..h {
                    for g in 0..groups {
                        let gr: [&[f32]; GROUP] = std::array::from_fn(|o| {
                            let channel = (g * GROUP + o).min(cout - 1);
                            &gs.row(channel, z, y)[..row]
                        });
                        for i in 0..cin {
                            for td in 0..K {
                                for th in 0..K {
                                    let xr = &xs.row(i, z + td, y + th)[..row + K - 1];
                                    for tw0 in (0..K).step_by(TAP_RUN) {
                                        let run = TAP_RUN.min(K - tw0);
                                        let mut v = [[f32x8::ZERO; TAP_RUN]; GROUP];
                                        for xb in (0..row).step_by(LANES) {
                                            let xv: [f32x8; TAP_RUN] = std::array::from_fn(|j| {
                                                load(&xr[(xb + tw0 + j).min(row + K - 1 - LANES)..])
                                            });
                                            for (o, v_o) in v.iter_mut().enumerate() {
                                                let gv = load(&gr[o][xb..]);
                                                for (a, xj) in v_o.iter_mut().zip(&xv) {
                                                    *a = xj.mul_add(gv, *a);
                                                }
                                            }
                                        }
                                        for (o, v_o) in v.iter().enumerate() {
                                            let base = (((g * GROUP + o) * cin + i) * K + td) * K + th;
                                            for (j, vj) in v_o.iter().enumerate().take(run) {
                                                acc[base * K + tw0 + j] += f64::from(vj.reduce_add());
                                            }
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
                acc
            },
        )
        .reduce(
            || vec![0f64; len],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x += y;
                }
                a
            },
        );
    sums[..cout * cin * taps].iter().map(|v| *v as f32).collect()
}

/// A transposed convolution (kernel 3, stride 2, padding 1, output padding 1; `weight`
/// `[cin][cout][3][3][3]` as PyTorch's ConvTranspose3d) as the kernel of a "same" convolution of
/// the zero-upsampled input: `out = conv3d_same(upsample2_zeros(x), transposed_as_conv(w))`.
pub fn transposed_as_conv(weight: &[f32], cin: usize, cout: usize) -> Vec<f32> {
    // ConvTranspose's [cin][cout] is the gradient kernel's layout of a conv [cout][cin]: the same
    // flip with the roles swapped.
    flip_transpose(weight, cin, cout, 3)
}

/// Weight gradient of a transposed convolution in PyTorch's `[cin][cout][3][3][3]` layout, from
/// the gradient of the equivalent convolution's weights ([`transposed_as_conv`]).
pub fn transposed_weight_grad(conv_grad: &[f32], cin: usize, cout: usize) -> Vec<f32> {
    flip_transpose(conv_grad, cout, cin, 3)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::super::reference;
    use super::*;

    /// A deterministic pseudo-random tensor in [−1, 1].
    pub(crate) fn random(shape: [usize; 4], seed: u64) -> Tensor {
        let n = shape.iter().product();
        Tensor {
            shape,
            data: random_values(n, seed),
        }
    }

    pub(crate) fn random_values(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = crate::rng::SplitMix64::new(seed);
        (0..n).map(|_| rng.uniform_f32(-1.0, 1.0)).collect()
    }

    fn assert_close(got: &[f32], expected: &[f32], tolerance: f32, what: &str) {
        assert_eq!(got.len(), expected.len(), "{what}");
        for (i, (a, b)) in got.iter().zip(expected).enumerate() {
            assert!((a - b).abs() <= tolerance * (1.0 + b.abs()), "{what}[{i}]: {a} vs {b}");
        }
    }

    #[test]
    fn a_convolution_accumulated_over_channel_groups_is_the_whole_one() {
        // 8 input channels as two groups of 4 (owned, each freed once padded), the bias with
        // the first, the ReLU after the last: `ReLU(conv(x) + bias)` by the plain loops.
        let (shape, cout, k) = ([8, 5, 6, 53], 4, 7);
        let x = random(shape, 1);
        let weight = random_values(cout * 8 * k * k * k, 2);
        let bias = random_values(cout, 3);
        let mut expected = reference::conv3d(&x, &weight, cout, k, 1);
        let plane = shape[1] * shape[2] * shape[3];
        for (c, chunk) in expected.data.chunks_mut(plane).enumerate() {
            for v in chunk {
                *v = (*v + bias[c]).max(0.0);
            }
        }
        let group = |g: usize| {
            let part = Tensor {
                shape: [4, shape[1], shape[2], shape[3]],
                data: x.data[4 * g * plane..4 * (g + 1) * plane].to_vec(),
            };
            let own = input_channels(&weight, cout, 8, k, 4 * g..4 * (g + 1));
            (part, own)
        };
        let (first, own) = group(0);
        let sum = conv3d_input(ConvInput::Owned(first), &own, cout, k, Some(&bias), Epilogue::default());
        let (second, own) = group(1);
        let got = conv3d_accumulate_input(ConvInput::Owned(second), &own, k, sum, true);
        assert_eq!(got.shape, expected.shape);
        assert_close(&got.data, &expected.data, 1e-4, "accumulated");
        assert!(got.data.contains(&0.0) && got.data.iter().any(|v| *v > 0.0));
    }

    #[test]
    fn the_wide_kernel_gives_the_256_bit_paths_bits() {
        if !wide_kernel::available() {
            println!("skipped: this host has no AVX-512F (only the 256-bit paths run)");
            return;
        }
        // Whole tiles, a partial last tile (with one whole block and a partial one: 77, 75), one
        // narrower than a tile; every kernel size, a ReLU and a stride-2 epilogue, with a bias;
        // two channel groups.
        let cases = [
            ([2, 3, 4, 96], 4, 3, 1),
            ([4, 3, 5, 101], 4, 5, 1),
            ([8, 2, 3, 144], 4, 7, 1),
            ([3, 4, 6, 53], 6, 3, 2),
            ([1, 2, 2, 40], 4, 7, 1),
            ([2, 3, 4, 77], 4, 3, 1),
            ([3, 2, 5, 75], 6, 5, 2),
            ([4, 2, 3, 120], 4, 7, 1),
        ];
        let same_bits = |wide: &Tensor, narrow: &Tensor, what: &str| {
            assert_eq!(wide.shape, narrow.shape, "{what}");
            let differing = wide
                .data
                .iter()
                .zip(&narrow.data)
                .filter(|(a, b)| a.to_bits() != b.to_bits())
                .count();
            assert_eq!(differing, 0, "{what}: {differing} values differ");
        };
        for (seed, (shape, cout, k, stride)) in cases.into_iter().enumerate() {
            let x = random(shape, 400 + seed as u64);
            let weight = random_values(cout * shape[0] * k * k * k, 500 + seed as u64);
            let bias = random_values(cout, 600 + seed as u64);
            let epilogue = Epilogue { relu: true, stride };
            let wide = conv3d_with(&x, &weight, cout, k, Some(&bias), epilogue);
            crate::wide::set_enabled(false);
            let narrow = conv3d_with(&x, &weight, cout, k, Some(&bias), epilogue);
            crate::wide::set_enabled(true);
            same_bits(&wide, &narrow, &format!("{shape:?} k{k} stride {stride}"));
        }
        // Written into the next layer's padded tiles, and added into a tensor, at widths with a
        // partial last tile.
        for (seed, shape) in [[3, 2, 4, 47], [4, 3, 3, 77]].into_iter().enumerate() {
            let (cout, k) = (4, 3);
            let x = random(shape, 700 + seed as u64);
            let weight = random_values(cout * shape[0] * k * k * k, 710 + seed as u64);
            let bias = random_values(cout, 720 + seed as u64);
            let prior = random([cout, shape[1], shape[2], shape[3]], 730 + seed as u64);
            let run = || {
                let padded = conv3d_padded(ConvInput::Borrowed(&x), &weight, cout, k, Some(&bias), true, 5).to_tensor();
                let added = conv3d_accumulate_input(ConvInput::Borrowed(&x), &weight, k, prior.clone(), true);
                (padded, added)
            };
            let (padded, added) = run();
            crate::wide::set_enabled(false);
            let (padded_narrow, added_narrow) = run();
            crate::wide::set_enabled(true);
            same_bits(&padded, &padded_narrow, &format!("{shape:?} into padded tiles"));
            same_bits(&added, &added_narrow, &format!("{shape:?} added into a tensor"));
        }
    }

    #[test]
    fn fast_convolution_matches_the_plain_loops_on_random_shapes() {
        // Widths around the 24-column block, the 48-column tile and the 8 lanes; channel counts
        // off the group of 4.
        let cases = [
            ([2, 3, 4, 101], 4, 7),
            ([3, 2, 3, 97], 5, 5),
            ([1, 2, 2, 49], 4, 3),
            ([1, 5, 6, 7], 4, 7),
            ([4, 3, 4, 25], 4, 5),
            ([8, 4, 5, 33], 4, 7),
            ([4, 6, 3, 48], 1, 3),
            ([3, 2, 3, 9], 6, 3),
            ([2, 3, 2, 5], 3, 1),
        ];
        for (seed, (shape, cout, k)) in cases.into_iter().enumerate() {
            let x = random(shape, seed as u64);
            let weight = random_values(cout * shape[0] * k * k * k, 100 + seed as u64);
            let bias = random_values(cout, 200 + seed as u64);
            let mut expected = reference::conv3d(&x, &weight, cout, k, 1);
            for (c, chunk) in expected
                .data
                .chunks_mut(expected.shape[1] * expected.shape[2] * expected.shape[3])
                .enumerate()
            {
                for v in chunk {
                    *v += bias[c];
                }
            }
            let got = conv3d_same(&x, &weight, cout, k, Some(&bias));
            assert_eq!(got.shape, expected.shape);
            assert_close(&got.data, &expected.data, 1e-4, &format!("forward {shape:?} k{k}"));

            // Input gradient: <grad, conv(x)> = <input_grad(grad), x> and the reference's form.
            let grad = random(got.shape, 300 + seed as u64);
            let input_grad = conv3d_same_input_grad(&grad, &weight, shape[0], k);
            let expected_input_grad =
                reference::conv3d(&grad, &flip_transpose(&weight, cout, shape[0], k), shape[0], k, 1);
            assert_close(&input_grad.data, &expected_input_grad.data, 1e-4, "input grad");
            let plain = reference::conv3d(&x, &weight, cout, k, 1);
            let lhs: f64 = grad.data.iter().zip(&plain.data).map(|(a, b)| f64::from(a * b)).sum();
            let rhs: f64 = input_grad.data.iter().zip(&x.data).map(|(a, b)| f64::from(a * b)).sum();
            assert!((lhs - rhs).abs() < 1e-3 * (1.0 + lhs.abs()), "adjoint {lhs} {rhs}");

            let weight_grad = conv3d_same_weight_grad(&x, &grad, k);
            let expected_weight_grad = reference::conv3d_weight_grad(&x, &grad, k);
            assert_close(&weight_grad, &expected_weight_grad, 1e-4, "weight grad");
        }
    }

    /// A one-channel input of `d × h × w` and random weights and biases for the chain `layers`
    /// (`(cin, cout, k)` each).
    fn chain_case(
        layers: &[(usize, usize, usize)],
        [d, h, w]: [usize; 3],
        seed: u64,
    ) -> (Tensor, Vec<Vec<f32>>, Vec<Vec<f32>>) {
        let x = random([1, d, h, w], seed);
        let weights = layers
            .iter()
            .enumerate()
            .map(|(i, &(cin, cout, k))| random_values(cout * cin * k * k * k, seed + 1 + i as u64))
            .collect();
        let biases = layers
            .iter()
            .enumerate()
            .map(|(i, &(_, cout, _))| random_values(cout, seed + 5 + i as u64))
            .collect();
        (x, weights, biases)
    }

    #[test]
    fn layers_that_write_the_next_ones_padded_tiles_give_the_plain_chain() {
        // Widths around the 48-column tile (halos on both sides of a boundary, a last tile of a
        // few columns), kernels 5 → 3 → 3 → 7 as a tower then a wider layer, and a padded
        // output read by a kernel it was not made for (copied again).
        for (seed, &[d, h, w]) in [[3usize, 4, 101], [2, 3, 49], [4, 2, 47], [2, 5, 9]].iter().enumerate() {
            let layers: [(usize, usize, usize); 4] = [(1, 4, 5), (4, 4, 3), (4, 4, 3), (4, 2, 7)];
            let (x, weights, biases) = chain_case(&layers, [d, h, w], seed as u64 * 10);
            let relu = Epilogue { stride: 1, relu: true };
            let mut plain = x.clone();
            for (((_, cout, k), weight), bias) in layers.iter().zip(&weights).zip(&biases) {
                plain = conv3d_with(&plain, weight, *cout, *k, Some(bias), relu);
            }
            let mut chained = ConvInput::Borrowed(&x);
            for i in 0..3 {
                let (_, cout, k) = layers[i];
                // The third layer's tiles are made for kernel 5, which the 7³ layer does not read.
                let next_k = if i == 2 { 5 } else { layers[i + 1].2 };
                let padded = conv3d_padded(chained, &weights[i], cout, k, Some(&biases[i]), true, next_k);
                assert_eq!(padded.shape(), [cout, d, h, w]);
                chained = ConvInput::Padded(padded);
            }
            let (_, cout, k) = layers[3];
            let got = conv3d_input(chained, &weights[3], cout, k, Some(&biases[3]), relu);
            assert_close(&got.data, &plain.data, 1e-4, &format!("chain over {d}x{h}x{w}"));
            // A padded output back to a tensor.
            let padded = conv3d_padded(ConvInput::Borrowed(&x), &weights[0], 4, 5, Some(&biases[0]), true, 3);
            let first = conv3d_with(&x, &weights[0], 4, 5, Some(&biases[0]), relu);
            assert_eq!(padded.to_tensor().data, first.data, "{d}x{h}x{w}");
        }
    }

    #[test]
    fn layers_that_write_the_next_ones_channel_pairs_give_the_same_bits() {
        // In bfloat16, a chain whose layers write the next one's channel pairs against the same
        // chain writing values (each layer then pairing its input itself): the same pairs, so
        // the same bits; the last paired output read by a layer of another kernel (values again,
        // as the pairs hold them) and back as a tensor; pairs refused by `combine`.
        if with_precision(Precision::Bf16, || effective_precision_for(3, 4)) != Precision::Bf16 {
            println!("skipped: this host has no AVX512-BF16 (no layer pairs channels)");
            return;
        }
        for (seed, &[d, h, w]) in [[3usize, 4, 101], [2, 3, 49], [2, 5, 9]].iter().enumerate() {
            let layers: [(usize, usize, usize); 4] = [(1, 4, 5), (4, 4, 3), (4, 4, 3), (4, 2, 3)];
            let (x, weights, biases) = chain_case(&layers, [d, h, w], seed as u64 * 10 + 3);
            let relu = Epilogue { stride: 1, relu: true };
            let run = |pairs: bool| {
                with_precision(Precision::Bf16, || {
                    let mut chained = ConvInput::Borrowed(&x);
                    for i in 0..3 {
                        let (_, cout, k) = layers[i];
                        let next_k = layers[i + 1].2;
                        let padded = if pairs {
                            conv3d_padded_pairs(chained, &weights[i], cout, k, Some(&biases[i]), true, next_k)
                        } else {
                            conv3d_padded(chained, &weights[i], cout, k, Some(&biases[i]), true, next_k)
                        };
                        assert_eq!(padded.0.channel_pairs, pairs, "layer {i}");
                        chained = ConvInput::Padded(padded);
                    }
                    let (_, cout, k) = layers[3];
                    conv3d_input(chained, &weights[3], cout, k, Some(&biases[3]), relu)
                })
            };
            let (paired, plain) = (run(true), run(false));
            assert_eq!(bits_differing(&paired, &plain), 0, "{d}x{h}x{w}");
            with_precision(Precision::Bf16, || {
                let made = |next_k: usize| {
                    conv3d_padded_pairs(
                        ConvInput::Borrowed(&x),
                        &weights[0],
                        4,
                        5,
                        Some(&biases[0]),
                        true,
                        next_k,
                    )
                };
                // Back as a tensor: each value in bfloat16.
                let first = conv3d_with(&x, &weights[0], 4, 5, Some(&biases[0]), relu);
                let rounded: Vec<f32> = first.data.iter().map(|&v| bf16_kernel::round_to_bf16(v)).collect();
                assert_eq!(made(3).to_tensor().data, rounded, "{d}x{h}x{w}");
                // Read by a 3³ layer from tiles made for 5, or by one in f32: the values as the
                // pairs hold them.
                let values = Tensor {
                    shape: first.shape,
                    data: rounded.clone(),
                };
                let by_other = conv3d_input(ConvInput::Padded(made(5)), &weights[1], 4, 3, None, relu);
                let from_values = conv3d_input(ConvInput::Borrowed(&values), &weights[1], 4, 3, None, relu);
                assert_eq!(bits_differing(&by_other, &from_values), 0, "{d}x{h}x{w}");
                let paired = made(3);
                let in_f32 = with_precision(Precision::F32, || {
                    (
                        conv3d_input(ConvInput::Padded(paired), &weights[1], 4, 3, None, relu),
                        conv3d_input(ConvInput::Borrowed(&values), &weights[1], 4, 3, None, relu),
                    )
                });
                assert_eq!(bits_differing(&in_f32.0, &in_f32.1), 0, "{d}x{h}x{w} in f32");
                let mut a = made(3);
                assert!(!a.combine(&made(3), |s, x| s + x), "pairs are not values to combine");
            });
        }
    }

    #[test]
    fn an_f32_layer_writes_the_pairs_a_bfloat16_layer_after_it_reads() {
        // On the matrix unit, `auto` runs a 3³ layer in f32 and the 7³ layer after it in
        // bfloat16: the 3³ layer writes its output as that layer's channel pairs, in whole
        // tiles and in the narrower last tile alike (widths 101, 49, 9). The 7³ layer then
        // gives the bits it gives when it pairs the same values itself.
        let precisions = with_precision(Precision::Auto, || {
            (effective_precision_for(3, 4), effective_precision_for(7, 4))
        });
        if precisions != (Precision::F32, Precision::Bf16) {
            println!("skipped: `auto` runs both kernels in one precision here ({precisions:?}; no matrix unit)");
            return;
        }
        for (seed, &[d, h, w]) in [[3usize, 4, 101], [2, 3, 49], [2, 5, 9]].iter().enumerate() {
            let layers: [(usize, usize, usize); 2] = [(4, 4, 3), (4, 4, 7)];
            let (x, weights, biases) = chain_case(&layers, [d, h, w], seed as u64 * 10 + 5);
            let relu = Epilogue { stride: 1, relu: true };
            with_precision(Precision::Auto, || {
                let padded = conv3d_padded_pairs(ConvInput::Borrowed(&x), &weights[0], 4, 3, Some(&biases[0]), true, 7);
                assert!(padded.0.channel_pairs, "{d}x{h}x{w}: pairs written");
                let paired = conv3d_input(ConvInput::Padded(padded), &weights[1], 4, 7, Some(&biases[1]), relu);
                let values = conv3d_with(&x, &weights[0], 4, 3, Some(&biases[0]), relu);
                let from_values = conv3d_input(ConvInput::Borrowed(&values), &weights[1], 4, 7, Some(&biases[1]), relu);
                assert_eq!(bits_differing(&paired, &from_values), 0, "{d}x{h}x{w}");
            });
        }
    }

    /// How many values of `got` are not bit for bit those of `expected` (all of them when the
    /// shapes differ).
    fn bits_differing(got: &Tensor, expected: &Tensor) -> usize {
        if got.shape != expected.shape {
            return got.data.len().max(1);
        }
        got.data
            .iter()
            .zip(&expected.data)
            .filter(|(a, b)| a.to_bits() != b.to_bits())
            .count()
    }

    #[test]
    fn a_thread_keeps_as_many_spares_as_it_is_allowed() {
        // Tests run on threads of their own, so this thread's limit is this test's.
        release_spares();
        let offer_ten = || (0..10).for_each(|_| offer_spare(vec![0.0; MIN_SPARE_FLOATS], None));
        offer_ten();
        assert_eq!(SPARES.with_borrow(Vec::len), DEFAULT_SPARES);
        release_spares();
        assert_eq!(keep_spares(8), DEFAULT_SPARES);
        offer_ten();
        assert_eq!(SPARES.with_borrow(Vec::len), 8);
        assert_eq!(keep_spares(DEFAULT_SPARES), 8);
        release_spares();
    }

    /// `|Σ w·x|` bounds: the convolution of `|x|` with `|w|` (no bias), the scale a bfloat16
    /// rounding error of the products is relative to.
    fn magnitude(x: &Tensor, weight: &[f32], cout: usize, k: usize, stride: usize) -> Tensor {
        let abs = Tensor {
            shape: x.shape,
            data: x.data.iter().map(|v| v.abs()).collect(),
        };
        let weight: Vec<f32> = weight.iter().map(|v| v.abs()).collect();
        conv3d_with(&abs, &weight, cout, k, None, Epilogue { stride, relu: false })
    }

    /// `x` convolved with `weight` (5 output channels, kernel `k`) and summed into a random
    /// tensor with the ReLU, in `precision` and in f32, with the [`magnitude`] bound.
    fn summed_in(precision: Precision, x: &Tensor, weight: &[f32], k: usize, seed: u64) -> (Tensor, Tensor, Tensor) {
        let [_, d, h, w] = x.shape;
        let prior = random([5, d, h, w], seed + 7);
        let exact = conv3d_accumulate_input(ConvInput::Borrowed(x), weight, k, prior.clone(), true);
        let got = with_precision(precision, || {
            conv3d_accumulate_input(ConvInput::Borrowed(x), weight, k, prior.clone(), true)
        });
        (got, exact, magnitude(x, weight, 5, k, 1))
    }

    /// Two layers (5³ to 4 channels, then 3³ to 2) chained through padded tiles in `precision`
    /// (a paired input must not be read again as values), against f32: the largest difference
    /// and the largest f32 value.
    fn chain_in(precision: Precision, x: &Tensor, seed: u64) -> (f32, f32) {
        let w1 = random_values(4 * x.shape[0] * 125, seed + 20);
        let w2 = random_values(2 * 4 * 27, seed + 21);
        let relu = Epilogue { stride: 1, relu: true };
        let exact = conv3d_with(&conv3d_with(x, &w1, 4, 5, None, relu), &w2, 2, 3, None, relu);
        let got = with_precision(precision, || {
            let first = conv3d_padded(ConvInput::Borrowed(x), &w1, 4, 5, None, true, 3);
            conv3d_input(ConvInput::Padded(first), &w2, 2, 3, None, relu)
        });
        let worst = got
            .data
            .iter()
            .zip(&exact.data)
            .map(|(g, e)| (g - e).abs())
            .fold(0f32, f32::max);
        (worst, exact.data.iter().map(|v| v.abs()).fold(0f32, f32::max))
    }

    #[test]
    fn bfloat16_convolutions_stay_within_the_rounding_of_their_products() {
        assert_eq!(effective_precision(3), Precision::F32, "this thread starts in f32");
        if with_precision(Precision::Bf16, || effective_precision(3)) != Precision::Bf16 {
            println!("skipped: this host has no AVX512-BF16 (bfloat16 asked for runs in f32)");
            return;
        }
        // Widths around the 48-column tile (a partial last tile of a few columns), every kernel
        // size, both strides, the ReLU, a sum into a tensor and a chain through padded tiles.
        for (seed, &[d, h, w]) in [[3usize, 4, 101], [2, 3, 49], [4, 2, 47], [2, 5, 9]].iter().enumerate() {
            let seed = seed as u64 * 10;
            let x = random([3, d, h, w], seed);
            for k in [3, 5, 7] {
                let weight = random_values(5 * 3 * k * k * k, seed + k as u64);
                let bias = random_values(5, seed + 2);
                for stride in [1, 2] {
                    for relu in [false, true] {
                        let epilogue = Epilogue { stride, relu };
                        let exact = conv3d_with(&x, &weight, 5, k, Some(&bias), epilogue);
                        let got = with_precision(Precision::Bf16, || {
                            conv3d_with(&x, &weight, 5, k, Some(&bias), epilogue)
                        });
                        let scale = magnitude(&x, &weight, 5, k, stride);
                        assert_eq!(got.shape, exact.shape);
                        for ((g, e), m) in got.data.iter().zip(&exact.data).zip(&scale.data) {
                            // Two roundings of 2⁻⁹ each per product, at worst all one way.
                            assert!(
                                (g - e).abs() <= 2.0 * m / 256.0 + 1e-6,
                                "k {k}, stride {stride}, relu {relu}, {d}x{h}x{w}: {g} against {e} (scale {m})"
                            );
                        }
                        // Not f32 under another name: some outputs differ.
                        if !relu && stride == 1 {
                            assert!(bits_differing(&got, &exact) > 0, "k {k}: bfloat16 gave f32's bits");
                        }
                    }
                }
                // Summed into a tensor.
                let (got, exact, scale) = summed_in(Precision::Bf16, &x, &weight, k, seed);
                for ((g, e), m) in got.data.iter().zip(&exact.data).zip(&scale.data) {
                    assert!((g - e).abs() <= 2.0 * m / 256.0 + 1e-6, "k {k} summed: {g} against {e}");
                }
            }
            // A chain through padded tiles: a paired input is not read again as values.
            let (worst, largest) = chain_in(Precision::Bf16, &x, seed);
            assert!(
                worst <= 0.02 * largest.max(1.0),
                "chain {d}x{h}x{w}: off by {worst} of {largest}"
            );
        }
        assert_eq!(
            effective_precision(3),
            Precision::F32,
            "the precision before is restored"
        );
    }

    #[test]
    fn integer_convolutions_stay_within_their_quantisation() {
        if with_precision(Precision::Int16, || effective_precision(3)) != Precision::Int16 {
            println!("skipped: no AVX2 integer kernel on this target (16-bit integers asked for run in f32)");
            return;
        }
        // One input channel has nothing to pair: f32.
        assert_eq!(
            with_precision(Precision::Int16, || effective_precision_for(3, 1)),
            Precision::F32
        );
        assert_eq!(
            with_precision(Precision::Int16, || effective_precision_for(1, 4)),
            Precision::F32
        );
        // Widths around the 48-column tile, every kernel size, odd and even channel counts, both
        // strides, the ReLU, a sum into a tensor and a chain through padded tiles.
        for (seed, &[c, d, h, w]) in [[3usize, 3, 4, 101], [4, 2, 3, 49], [2, 4, 2, 47], [5, 2, 5, 9]]
            .iter()
            .enumerate()
        {
            let seed = seed as u64 * 10 + 1;
            let x = random([c, d, h, w], seed);
            let largest_x = x.data.iter().map(|v| v.abs()).fold(0f32, f32::max);
            let x_abs = Tensor {
                shape: x.shape,
                data: x.data.iter().map(|v| v.abs()).collect(),
            };
            for k in [3, 5, 7] {
                let weight = random_values(5 * c * k * k * k, seed + k as u64);
                let bias = random_values(5, seed + 2);
                // Per output channel: the weight step (at most the largest weight / 2¹⁵ or the
                // widest pair's L1 norm / 2¹⁷) and the sum of |w|.
                let taps = c * k * k * k;
                let steps: Vec<f32> = weight
                    .chunks(taps)
                    .map(|w_o| {
                        let largest = w_o.iter().map(|v| v.abs()).fold(0f32, f32::max);
                        let widest = w_o
                            .chunks(2 * k * k * k)
                            .map(|p| p.iter().map(|v| v.abs()).sum::<f32>())
                            .fold(0f32, f32::max);
                        0.5 * (largest / 32767.0).max(widest / 130_000.0)
                    })
                    .collect();
                let x_step = 0.5 * largest_x / int16_kernel::INPUT_LEVELS;
                for stride in [1, 2] {
                    for relu in [false, true] {
                        let epilogue = Epilogue { stride, relu };
                        let exact = conv3d_with(&x, &weight, 5, k, Some(&bias), epilogue);
                        let got = with_precision(Precision::Int16, || {
                            conv3d_with(&x, &weight, 5, k, Some(&bias), epilogue)
                        });
                        // Σ|x| over each output's taps: the convolution of |x| with ones.
                        let x_sums = conv3d_with(
                            &x_abs,
                            &vec![1.0; 5 * taps],
                            5,
                            k,
                            None,
                            Epilogue { stride, relu: false },
                        );
                        let w_sums = magnitude(
                            &Tensor {
                                shape: x.shape,
                                data: vec![1.0; x.data.len()],
                            },
                            &weight,
                            5,
                            k,
                            stride,
                        );
                        assert_eq!(got.shape, exact.shape);
                        let plane = got.shape[1] * got.shape[2] * got.shape[3];
                        for (i, (g, e)) in got.data.iter().zip(&exact.data).enumerate() {
                            let o = i / plane;
                            let bound = x_sums.data[i] * steps[o]
                                + w_sums.data[i] * x_step
                                + taps as f32 * steps[o] * x_step
                                + 1e-5 * (1.0 + e.abs());
                            assert!(
                                (g - e).abs() <= bound,
                                "k {k}, {c} channels, stride {stride}, relu {relu}, {d}x{h}x{w}: {g} against {e} (bound {bound})"
                            );
                        }
                        if !relu && stride == 1 {
                            assert!(
                                bits_differing(&got, &exact) > 0,
                                "k {k}: 16-bit integers gave f32's bits"
                            );
                        }
                    }
                }
                // Summed into a tensor.
                let (got, exact, scale) = summed_in(Precision::Int16, &x, &weight, k, seed);
                for ((g, e), m) in got.data.iter().zip(&exact.data).zip(&scale.data) {
                    assert!((g - e).abs() <= 0.01 * (m + 1.0), "k {k} summed: {g} against {e}");
                }
            }
            // A chain through padded tiles: a paired input is not read again as values.
            let (worst, largest) = chain_in(Precision::Int16, &x, seed);
            assert!(
                worst <= 0.01 * largest.max(1.0),
                "chain {d}x{h}x{w}: off by {worst} of {largest}"
            );
        }
        assert_eq!(
            effective_precision(3),
            Precision::F32,
            "the precision before is restored"
        );
    }

    #[test]
    fn a_spare_left_by_a_bfloat16_layer_has_its_border_zeroed_again() {
        if with_precision(Precision::Bf16, || effective_precision(3)) != Precision::Bf16 {
            println!("skipped: this host has no AVX512-BF16");
            return;
        }
        // Large enough to be kept as a spare (`MIN_SPARE_FLOATS`): the bfloat16 layer's padded
        // input (shifted pairs, a zero beside a value no longer zero) is offered without its
        // layout, and the next f32 layer of that layout zeroes its border before use.
        let x = random([4, 8, 60, 100], 31);
        let weight = random_values(4 * 4 * 27, 32);
        let relu = Epilogue { stride: 1, relu: true };
        release_spares();
        let expected = std::thread::scope(|s| {
            s.spawn(|| conv3d_with(&x, &weight, 4, 3, None, relu))
                .join()
                .unwrap_or_else(|_| panic!("the reference thread panicked"))
        });
        with_precision(Precision::Bf16, || conv3d_with(&x, &weight, 4, 3, None, relu));
        assert!(
            SPARES.with_borrow(|s| s.iter().any(|(_, layout)| layout.is_none())),
            "the paired input is kept without its layout"
        );
        let got = conv3d_with(&x, &weight, 4, 3, None, relu);
        release_spares();
        assert_eq!(bits_differing(&got, &expected), 0);
    }

    #[test]
    fn padded_tiles_in_dirty_spare_buffers_give_the_plain_convolutions() {
        // Every layer's padded input and output taken from spares full of NaN (old values of
        // another layer): only the values written and the zeroed border may be read.
        for &[d, h, w] in &[[3usize, 4, 101], [2, 3, 49], [4, 2, 47], [2, 5, 9]] {
            let x = random([1, d, h, w], 3);
            let (w1, w2) = (random_values(4 * 125, 4), random_values(2 * 4 * 27, 5));
            let relu = Epilogue { stride: 1, relu: true };
            release_spares();
            let expected_first = conv3d_with(&x, &w1, 4, 5, None, relu);
            let expected = conv3d_with(&expected_first, &w2, 2, 3, None, relu);
            // The first layer's padded input (1 channel, border 2, rows of 52) and padded
            // output (4 channels, border 1, rows of 50).
            let tiles = w.div_ceil(TILE_BLOCKS * BLOCK);
            offer_spare(vec![f32::NAN; tiles * (d + 4) * (h + 4) * 52], None);
            offer_spare(vec![f32::NAN; tiles * 4 * (d + 2) * (h + 2) * 50], None);
            let first = conv3d_padded(ConvInput::Borrowed(&x), &w1, 4, 5, None, true, 3);
            let got = conv3d_input(ConvInput::Padded(first), &w2, 2, 3, None, relu);
            // Both taken (buffers this small are not kept again).
            assert_eq!(SPARES.with_borrow(Vec::len), 0, "{d}x{h}x{w}: spares left unused");
            assert_eq!(bits_differing(&got, &expected), 0, "{d}x{h}x{w}: values that differ");
            release_spares();
        }
    }

    #[test]
    fn a_spare_of_the_same_layout_keeps_its_zero_border_and_gives_the_plain_convolutions() {
        // A chain of 3³ layers, whose padded tiles share one layout: each output goes into the
        // buffer its input's input held, whose interior is set to NaN here before it is taken;
        // only its border, kept from before, is read unwritten.
        let [d, h, w] = [2usize, 40, 700];
        let x = random([4, d, h, w], 6);
        let weights: Vec<Vec<f32>> = (0..3).map(|i| random_values(4 * 4 * 27, 7 + i)).collect();
        let relu = Epilogue { stride: 1, relu: true };
        release_spares();
        let mut plain = x.clone();
        for weight in &weights {
            plain = conv3d_with(&plain, weight, 4, 3, None, relu);
        }
        let mut input = PaddedTensor::of(&x, 3);
        let layout = Layout {
            shape: [4, d, h, w],
            p: 1,
            step: input.0.step,
            row: input.0.row,
        };
        let block = (h + 2) * 4 * layout.row;
        let mut spoiled = 0;
        for weight in &weights {
            input = conv3d_padded(ConvInput::Padded(input), weight, 4, 3, None, true, 3);
            SPARES.with_borrow_mut(|spares| {
                for (data, _) in spares.iter_mut().filter(|(_, held)| *held == Some(layout)) {
                    data.fill(f32::NAN);
                    for (i, chunk) in data.chunks_mut(block).enumerate() {
                        layout.zero_border(chunk, i / (d + 2), i % (d + 2));
                    }
                    spoiled += 1;
                }
            });
        }
        assert!(spoiled >= 2, "spares of the same layout: {spoiled}");
        let got = input.to_tensor();
        assert_eq!(bits_differing(&got, &plain), 0, "values that differ");
        // Such a spare is taken as it is; one of another layout has its border zeroed.
        release_spares();
        let len = input.0.data.len();
        offer_spare(vec![1.0; len], Some(layout));
        assert!(!spare_buffer(len, layout).1);
        offer_spare(vec![1.0; len], Some(Layout { p: 2, ..layout }));
        assert!(spare_buffer(len, layout).1);
        // One more than twice as large is left for a larger tensor.
        offer_spare(vec![1.0; 2 * len + 1], None);
        assert_eq!(spare_buffer(len, layout), (vec![0.0; len], false));
        assert_eq!(scratch_buffer(len).len(), len);
        assert_eq!(SPARES.with_borrow(Vec::len), 1);
        release_spares();
    }

    #[test]
    fn a_window_is_convolved_as_its_crop() {
        let x = random([3, 4, 9, 103], 11);
        let weight = random_values(4 * 3 * 27, 12);
        let relu = Epilogue { stride: 1, relu: true };
        // Inside, at the edges, and reaching past them (clamped).
        for (rows, columns) in [(2..7, 5..90), (0..9, 0..103), (3..20, 50..200), (4..4, 0..10)] {
            let crop = x.crop_hw(rows.clone(), columns.clone());
            let expected = conv3d_with(&crop, &weight, 4, 3, None, relu);
            let window = ConvInput::Window(&x, rows.clone(), columns.clone());
            assert_eq!(window.shape(), crop.shape, "{rows:?} × {columns:?}");
            let got = conv3d_input(window, &weight, 4, 3, None, relu);
            assert_eq!(got, expected, "{rows:?} × {columns:?}");
        }
    }

    #[test]
    fn the_epilogue_equals_subsampling_and_relu_after_the_convolution() {
        for (seed, (shape, cout, k)) in [([3, 5, 7, 53], 4, 3), ([2, 4, 6, 30], 5, 7), ([1, 3, 3, 97], 4, 5)]
            .into_iter()
            .enumerate()
        {
            let x = random(shape, 400 + seed as u64);
            let weight = random_values(cout * shape[0] * k * k * k, 500 + seed as u64);
            let bias = random_values(cout, 600 + seed as u64);
            let plain = conv3d_same(&x, &weight, cout, k, Some(&bias));
            for (stride, relu) in [(1, true), (2, false), (2, true)] {
                let mut expected = if stride == 2 { plain.subsample2() } else { plain.clone() };
                if relu {
                    expected = expected.relu();
                }
                let got = conv3d_with(&x, &weight, cout, k, Some(&bias), Epilogue { stride, relu });
                assert_eq!(got.shape, expected.shape, "{shape:?} stride {stride}");
                assert_eq!(got.data, expected.data, "{shape:?} stride {stride} relu {relu}");
            }
        }
    }

    #[test]
    fn strided_and_transposed_convolutions_through_the_same_convolution() {
        for (seed, shape) in [[4, 4, 6, 10], [4, 5, 7, 9]].into_iter().enumerate() {
            let x = random(shape, 10 + seed as u64);
            let weight = random_values(4 * 4 * 27, 20 + seed as u64);
            let strided = conv3d_same(&x, &weight, 4, 3, None).subsample2();
            let expected = reference::conv3d(&x, &weight, 4, 3, 2);
            assert_eq!(strided.shape, expected.shape);
            assert_close(&strided.data, &expected.data, 1e-4, "stride 2");

            let transposed = conv3d_same(
                &x.upsample2_zeros([2 * shape[1], 2 * shape[2], 2 * shape[3]]),
                &transposed_as_conv(&weight, 4, 4),
                4,
                3,
                None,
            );
            let expected = reference::conv_transpose3d(&x, &weight, 4);
            assert_eq!(transposed.shape, expected.shape);
            assert_close(&transposed.data, &expected.data, 1e-4, "transposed");
        }
    }
}
