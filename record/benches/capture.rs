//! Criterion benchmarks of the recording path, reported as ratios within one run: one 1080p view
//! at 4 samples per pixel against 1 sample (the anti-aliasing cost), and a whole five-view set
//! written as raw images against PNG (the encoding cost). The absolute issue-2 figure (a
//! five-view 1920×1080 capture ≤ 15 s, ≤ 1.5 GB) comes from `scripts/bench-record.sh`.

#![allow(missing_docs)]

use std::hint::black_box;
use std::sync::atomic::AtomicBool;

use criterion::{Criterion, criterion_group, criterion_main};
use record::ImageFormat;
use record::camera::PinholeCamera;
use record::capture::{Simulation, SimulationConfig, default_hand_eye, look_at};
use record::log::LogOptions;
use record::render::{PreparedScene, RenderSettings};
use record::scene::{Scene, SceneKind};

fn render_view(c: &mut Criterion) {
    let scene = Scene::build(SceneKind::Toy, 0);
    let prepared = PreparedScene::new(&scene);
    let camera = PinholeCamera::from_horizontal_fov(1920, 1080, 60.0);
    let pose = look_at(
        nalgebra::Point3::new(0.8, 0.0, scene.camera_height_m),
        nalgebra::Point3::new(0.8, 0.0, 0.0),
        nalgebra::Vector3::x(),
    );
    let mut group = c.benchmark_group("render_1080p_view");
    group.sample_size(10);
    for samples in [1, 4] {
        let settings = RenderSettings {
            samples_per_pixel: samples,
            ..RenderSettings::default()
        };
        group.bench_function(format!("{samples}spp"), |b| {
            b.iter(|| black_box(prepared.render(&camera, &pose, &settings)))
        });
    }
    group.finish();
}

fn write_set(c: &mut Criterion) {
    let config = SimulationConfig::default();
    let set = match Simulation::new(config).and_then(|mut sim| sim.capture_set(0, &AtomicBool::new(false), |_| {})) {
        Ok(Some(set)) => set,
        other => panic!("simulation failed: {:?}", other.err()),
    };
    let hand_eye = default_hand_eye();
    let mut group = c.benchmark_group("write_five_view_set");
    group.sample_size(10);
    for format in [ImageFormat::Raw, ImageFormat::Png] {
        group.bench_function(format!("{format:?}"), |b| {
            b.iter(|| {
                let mut log = LogOptions::new()
                    .image_format(format)
                    .create(std::io::Cursor::new(Vec::with_capacity(64 << 20)))
                    .unwrap_or_else(|e| panic!("{e}"));
                log.write_set(&set, Some(&hand_eye)).unwrap_or_else(|e| panic!("{e}"));
                black_box(log.finish().unwrap_or_else(|e| panic!("{e}")).into_inner().len())
            })
        });
    }
    group.finish();
}

criterion_group!(benches, render_view, write_set);
criterion_main!(benches);
