//! How near the host's FMA peak each layer of MFuseNet runs: the peak measured
//! first (independent chains of 8-lane fused multiply-adds on every rayon thread), then each
//! layer of the eval-mode forward pass timed on its own at a fixed shape, with the multiply-adds
//! it computes (the stride-2 layers only their kept outputs; the transposed ones the
//! zero-upsampled input they convolve), its GFLOP/s and its share of the peak.
//!
//! `MIMALLOC_PURGE_DELAY=-1 cargo run --release -p fuse --example mfusenet_layers [D H W [N]]`
//! (default 36 136 240 4: the demo's 36 slices on a quarter of its 960 × 540 image, the
//! five-view network's four volumes; N = 2 is the three-view network; `lite` anywhere among the
//! arguments: the lite architecture's kernels; `narrow`: the 256-bit paths only, on a host with
//! AVX-512F, whose 512-bit kernel the layers otherwise take; `bf16`: the 3³–7³ layers in
//! bfloat16 products where the host has AVX512-BF16; `int16`: in 16-bit integer products on AVX2,
//! `fuse::nn::conv::Precision`). The figures are in
//! docs/benchmarks.md ("MFuseNet per layer").

use std::hint::black_box;
use std::time::Instant;

use fuse::mfusenet::network::ConvKind;
use fuse::mfusenet::{Architecture, Network};
use fuse::nn::Tensor;
use rayon::prelude::*;
use wide::f32x8;

/// The allocator `replay` runs the network with (run with `MIMALLOC_PURGE_DELAY=-1`, as `replay`
/// sets it, so that a layer's output reuses the pages of the one before instead of faulting
/// fresh ones).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// FLOP/s of independent 8-lane FMA chains on every thread (12 accumulators per thread: more
/// than the FMA latency × throughput of any x86 core, so the pipes stay full).
fn fma_peak() -> f64 {
    let threads = rayon::current_num_threads();
    let steps: usize = 20_000_000;
    let run = || {
        (0..threads)
            .into_par_iter()
            .map(|t| {
                let mut acc = [f32x8::splat(t as f32 * 1e-3); 12];
                let a = f32x8::splat(0.999_999);
                let b = f32x8::splat(1e-7);
                for _ in 0..steps {
                    for x in &mut acc {
                        *x = x.mul_add(a, b);
                    }
                }
                acc.iter().map(|x| x.reduce_add()).sum::<f32>()
            })
            .sum::<f32>()
    };
    black_box(run());
    let start = Instant::now();
    black_box(run());
    let seconds = start.elapsed().as_secs_f64();
    (threads * steps * 12 * 8 * 2) as f64 / seconds
}

fn tensor(shape: [usize; 4], seed: usize) -> Tensor {
    let n = shape.iter().product::<usize>();
    Tensor {
        shape,
        data: (0..n).map(|i| ((i * 7 + seed * 13) % 101) as f32 / 101.0).collect(),
    }
}

/// Times `f` (best of three).
fn best_of_three<T>(mut f: impl FnMut() -> T) -> f64 {
    (0..3)
        .map(|_| {
            let start = Instant::now();
            black_box(f());
            start.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() {
    let args: Vec<usize> = std::env::args().skip(1).filter_map(|a| a.parse().ok()).collect();
    let ([d, h, w], views) = match args.as_slice() {
        [d, h, w, views] => ([*d, *h, *w], *views),
        [d, h, w] => ([*d, *h, *w], 4),
        _ => ([36, 136, 240], 4),
    };
    if std::env::args().any(|a| a == "narrow") {
        fuse::wide::set_enabled(false);
    }
    let precision = if std::env::args().any(|a| a == "bf16") {
        fuse::nn::conv::Precision::Bf16
    } else if std::env::args().any(|a| a == "int16") {
        fuse::nn::conv::Precision::Int16
    } else {
        fuse::nn::conv::Precision::F32
    };
    fuse::nn::conv::with_precision(precision, || run([d, h, w], views));
}

fn run([d, h, w]: [usize; 3], views: usize) {
    let peak = fma_peak();
    println!(
        "host FMA peak: {:.1} GFLOP/s on {} threads (f32, 8 lanes)",
        peak / 1e9,
        rayon::current_num_threads()
    );
    let architecture = if std::env::args().any(|a| a == "lite") {
        Architecture::Lite
    } else {
        Architecture::Paper
    };
    println!(
        "convolutions on {}-bit vectors, {:?} products in the 3³ layers",
        if fuse::nn::wide_kernel::available() { 512 } else { 256 },
        fuse::nn::conv::effective_precision(3)
    );
    let net = Network::init_with(views, architecture, 1);
    let voxels = d * h * w;
    println!(
        "{} network for {views} volumes, input {d} × {h} × {w} ({voxels} voxels per volume)",
        architecture.name()
    );
    println!("| layer | k | in → out | output voxels | GFLOP | seconds | GFLOP/s | of peak |");
    println!("|---|---|---|---|---|---|---|---|");
    let mut total_flop = 0.0;
    let mut total_seconds = 0.0;
    // Each layer at the resolution it runs at in the forward pass (`Network::logits`).
    let full = [d, h, w];
    let half = [d / 2, h / 2, w / 2];
    let quarter = [d / 4, h / 4, w / 4];
    let feature_runs = net.feature.iter().map(|layer| (layer, full, views));
    let fuse_levels = [
        full, full, half, half, quarter, quarter, quarter, half, half, full, full,
    ];
    for (layer, [ld, lh, lw], repeats) in feature_runs.chain(net.fuse.iter().zip(fuse_levels).map(|(l, s)| (l, s, 1))) {
        let [cout, cin, k, ..] = layer.weight_shape();
        // Transposed layers store `[cin][cout]`: the convolution reads `cout` channels there.
        let (cin, cout) = match layer.kind {
            ConvKind::Up => (cout, cin),
            _ => (cin, cout),
        };
        let x = tensor([cin, ld, lh, lw], 1);
        let seconds = best_of_three(|| layer.forward_eval(&x)) * repeats as f64;
        let computed = match layer.kind {
            ConvKind::Same => ld * lh * lw,
            ConvKind::Down => (ld / 2) * (lh / 2) * (lw / 2),
            ConvKind::Up => 8 * ld * lh * lw,
        };
        let flop = 2.0 * (computed * cin * cout * k * k * k) as f64 * repeats as f64;
        total_flop += flop;
        total_seconds += seconds;
        let name = if repeats > 1 {
            format!("{} (× {repeats} views)", layer.name)
        } else {
            layer.name.clone()
        };
        println!(
            "| {name} | {k} | {cin} → {cout} | {computed} | {:.2} | {seconds:.3} | {:.1} | {:.0} % |",
            flop / 1e9,
            flop / seconds / 1e9,
            100.0 * flop / seconds / peak
        );
    }
    println!(
        "| all layers | | | | {:.2} | {total_seconds:.3} | {:.1} | {:.0} % |",
        total_flop / 1e9,
        total_flop / total_seconds / 1e9,
        100.0 * total_flop / total_seconds / peak
    );
    println!("multiply-adds per input voxel: {:.0}", total_flop / 2.0 / voxels as f64);
}
