//! Criterion benchmark of next-best-view planning (`fuse::plan`) at 960×540, read as a ratio
//! within one run: the planner against the block matching it plans from (SGM and MFuseNet are
//! slower still; `replay plan --json` reports both times on a real capture, docs/benchmarks.md).

#![allow(missing_docs)]

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use fuse::plan::{LayoutRule, PlanConfig, PlanInput, plan};
use fuse::{Image, Neighbour, Problem};

/// A textured scene with a near box on the left, seen from the centre and the left and right.
fn scene(width: usize, height: usize) -> (Problem, Vec<f32>) {
    let disparity = |x: usize| if x < width / 3 { 24.0 } else { 10.0 };
    let texture = |u: f64, v: f64| -> u8 {
        (128.0 + 60.0 * (u * 0.37).sin() * (v * 0.23).cos() + 40.0 * (u * 0.11 + v * 0.29).sin()) as u8
    };
    let render = |ox: f64| {
        let grey: Vec<u8> = (0..width * height)
            .map(|p| texture((p % width) as f64 + ox * disparity(p % width), (p / width) as f64))
            .collect();
        Image::gray(width, height, grey).unwrap_or_else(|e| panic!("{e}"))
    };
    let reference = render(0.0);
    let luma = reference.data.iter().map(|v| f32::from(*v)).collect();
    let neighbour = |role: &str, ox: i32| Neighbour {
        role: role.into(),
        image: render(f64::from(ox)),
        offset: [ox, 0],
        baseline_ratio: 1.0,
    };
    let problem = Problem {
        reference,
        neighbours: vec![neighbour("left", -1), neighbour("right", 1)],
        min_disparity: 0,
        num_disparities: 32,
    };
    (problem, luma)
}

fn planning(c: &mut Criterion) {
    let (width, height) = (960, 540);
    let (problem, luma) = scene(width, height);
    let method = fuse::methods::build("bm-heuristic", None).unwrap_or_else(|e| panic!("{e}"));
    let estimate = method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
    let confidence = estimate.confidence.clone().unwrap_or_else(|| vec![0.5; width * height]);
    let input = PlanInput {
        width,
        height,
        luma: &luma,
        disparity_px: &estimate.data,
        confidence: &confidence,
        taken: &[[-1, 0], [1, 0]],
        max_disparity_px: 256.0,
        expected_range_px: None,
    };
    let mut group = c.benchmark_group("plan_960x540");
    group.sample_size(10);
    group.bench_function("bm-heuristic (the method planned from)", |b| {
        b.iter(|| black_box(method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{e}"))))
    });
    for layout in [LayoutRule::Free, LayoutRule::Pairs] {
        let config = PlanConfig {
            layout,
            ..PlanConfig::default()
        };
        group.bench_function(format!("plan {layout:?}"), |b| {
            b.iter(|| black_box(plan(&input, &config).unwrap_or_else(|e| panic!("{e}"))))
        });
    }
    group.finish();
}

criterion_group!(benches, planning);
criterion_main!(benches);
