//! Criterion benchmarks of the work `replay` does around a method on a 1920×1080 set: the
//! occlusion mask from the ground truth, the evaluation (regions and the sparsification curve)
//! and the result files. `scripts/bench-replay.py` measures the whole process against the method
//! (the goal: wall time ≤ 1.2 × the method's); these say which part to look at.

#![allow(missing_docs)]

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use fuse::rng::SplitMix64;

const WIDTH: usize = 1920;
const HEIGHT: usize = 1080;

/// A floor at 20 px with 200 boxes at 30–120 px in front of it (steps that hide strips in every
/// neighbour), a strip of unknown truth along the top.
fn truth() -> Vec<f32> {
    let mut rng = SplitMix64::new(7);
    let mut below = |n: usize| rng.below(n as u64) as usize;
    let mut disparity = vec![20.0f32; WIDTH * HEIGHT];
    for _ in 0..200 {
        let (x0, y0) = (below(WIDTH), below(HEIGHT));
        let (w, h) = (20 + below(200), 20 + below(200));
        let d = 30.0 + below(9000) as f32 / 100.0;
        for y in y0..(y0 + h).min(HEIGHT) {
            for value in &mut disparity[y * WIDTH + x0..y * WIDTH + (x0 + w).min(WIDTH)] {
                *value = value.max(d);
            }
        }
    }
    disparity[..WIDTH * 8].fill(f32::NAN);
    disparity
}

fn process(c: &mut Criterion) {
    let truth = truth();
    let mut group = c.benchmark_group("process_1920x1080");
    group.sample_size(20);
    group.bench_function("occlusion_mask_cross", |b| {
        b.iter(|| {
            let mut hidden = vec![false; WIDTH * HEIGHT];
            replay::regions::mark_occluded_all(&truth, WIDTH, HEIGHT, &[[1, 0], [-1, 0], [0, 1], [0, -1]], &mut hidden);
            black_box(hidden)
        });
    });
    for (name, offsets) in [
        ("occlusion_mask_rows", [[1, 0], [-1, 0]]),
        ("occlusion_mask_columns", [[0, 1], [0, -1]]),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| {
                let mut hidden = vec![false; WIDTH * HEIGHT];
                replay::regions::mark_occluded_all(&truth, WIDTH, HEIGHT, &offsets, &mut hidden);
                black_box(hidden)
            });
        });
    }
    let hidden = replay::regions::hidden_from_axis_views(WIDTH, &truth);
    let mut rng = SplitMix64::new(11);
    let mut below = |n: u64| rng.below(n);
    let estimate: Vec<f32> = truth
        .iter()
        .map(|t| {
            if below(50) == 0 {
                f32::INFINITY
            } else {
                t + below(400) as f32 / 100.0 - 2.0
            }
        })
        .collect();
    let confidence: Vec<f32> = (0..estimate.len()).map(|_| below(1000) as f32 / 1000.0).collect();
    group.bench_function("region_metrics_with_confidence", |b| {
        b.iter(|| {
            black_box(replay::regions::region_metrics(
                &estimate,
                Some(&confidence),
                &truth,
                &hidden,
                None,
                128.0,
            ))
        });
    });
    let dir = std::env::temp_dir().join(format!("replay-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
    let rgb: Vec<u8> = (0..WIDTH * HEIGHT * 3).map(|i| (i % 251) as u8).collect();
    let path = dir.join("points.ply");
    group.bench_function("points_ply", |b| {
        b.iter(|| {
            viz::files::write_ply_points(
                &path,
                (WIDTH, HEIGHT),
                &estimate,
                0.0,
                &rgb,
                [1400.0, 1400.0, 960.0, 540.0],
                0.02,
            )
            .unwrap_or_else(|e| panic!("{e}"))
        });
    });
    group.bench_function("colormap_png", |b| {
        b.iter(|| {
            viz::files::write_colormap_png(&dir, "colormap", WIDTH, HEIGHT, &estimate, (0.0, 128.0))
                .unwrap_or_else(|e| panic!("{e}"))
        });
    });
    let pfm = dir.join("confidence.pfm");
    group.bench_function("confidence_pfm", |b| {
        b.iter(|| viz::files::write_pfm(&pfm, WIDTH, HEIGHT, &confidence).unwrap_or_else(|e| panic!("{e}")));
    });
    let png = dir.join("confidence.png");
    group.bench_function("confidence_png16", |b| {
        b.iter(|| viz::files::write_unit_png16(&png, WIDTH, HEIGHT, &confidence).unwrap_or_else(|e| panic!("{e}")));
    });
    group.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

criterion_group!(benches, process);
criterion_main!(benches);
