//! Criterion benchmarks of the methods on a synthetic five-view problem (a textured slanted
//! plane, 640×360, 64 disparities), read as ratios within one run: fused methods against their
//! stereo baseline, SGM against block matching, SGM with the weighted median against without.
//! The absolute figures against OpenCV come from `scripts/bench-replay.py` (graph cuts:
//! `scripts/bench-gc.sh`).

#![allow(missing_docs)]

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use fuse::{Image, Neighbour, Problem};

/// A pseudo-random texture on a slanted plane, seen from the centre and four neighbours.
fn problem(width: usize, height: usize, num_disparities: usize) -> Problem {
    let texture = |u: f64, v: f64| -> [u8; 3] {
        let h = ((u * 12.9898 + v * 78.233).sin() * 43758.5453).fract().abs();
        let g = (128.0 + 100.0 * (u * 0.37).sin() * (v * 0.23).cos() + 27.0 * h) as u8;
        [g, g.wrapping_add(40), g.wrapping_sub(30)]
    };
    let disparity = |x: usize| 8.0 + 40.0 * x as f64 / width as f64;
    let render = |ox: f64, oy: f64| {
        let mut rgb = Vec::with_capacity(width * height * 3);
        for y in 0..height {
            for x in 0..width {
                let d = disparity(x);
                rgb.extend_from_slice(&texture(x as f64 + ox * d, y as f64 + oy * d));
            }
        }
        Image::rgb(width, height, rgb).unwrap_or_else(|e| panic!("{e}"))
    };
    let neighbour = |role: &str, offset: [i32; 2]| Neighbour {
        role: role.into(),
        image: render(f64::from(offset[0]), f64::from(offset[1])),
        offset,
        baseline_ratio: 1.0,
    };
    Problem {
        reference: render(0.0, 0.0),
        neighbours: vec![
            neighbour("left", [-1, 0]),
            neighbour("right", [1, 0]),
            neighbour("top", [0, -1]),
            neighbour("bottom", [0, 1]),
        ],
        min_disparity: 0,
        num_disparities,
    }
}

fn methods(c: &mut Criterion) {
    let problem = problem(640, 360, 64);
    let mut group = c.benchmark_group("methods_640x360x64");
    group.sample_size(10);
    for name in ["bm-stereo", "bm-heuristic", "sgm-stereo", "sgm-heuristic"] {
        let method = fuse::methods::build(name, None).unwrap_or_else(|e| panic!("{e}"));
        group.bench_function(name, |b| b.iter(|| black_box(method.run(&problem, &|_| {}))));
    }
    // SGM over a stored byte volume against its costs made in the passes (the default).
    let stored = serde_json::json!({"costs_in_passes": false});
    let method = fuse::methods::build("sgm-heuristic", Some(&stored)).unwrap_or_else(|e| panic!("{e}"));
    group.bench_function("sgm-heuristic_stored_volume", |b| {
        b.iter(|| black_box(method.run(&problem, &|_| {})))
    });
    // The opt-in image-guided weighted median (MFuseNet's default) on top of SGM.
    let weighted = serde_json::json!({"weighted_median": {}});
    let method = fuse::methods::build("sgm-heuristic", Some(&weighted)).unwrap_or_else(|e| panic!("{e}"));
    group.bench_function("sgm-heuristic_weighted_median", |b| {
        b.iter(|| black_box(method.run(&problem, &|_| {})))
    });
    // The fused, box-aggregated costs alone (the stage block matching and SGM share), handed
    // to a sink that only reads them: the rest of block matching is the winners and filters.
    // Block matching's costs (Birchfield–Tomasi, 9×9) and SGM's (census 7×7, 7×7), the census
    // distances also on the 256-bit kernel where the host would take the 512-bit one (`fuse::wide`).
    let census = fuse::cost::PixelCost::Census {
        radius: 3,
        symmetric: false,
    };
    for (name, pixel, block_radius_px, wide) in [
        (
            "fused_costs_heuristic",
            fuse::cost::PixelCost::BirchfieldTomasi,
            4,
            true,
        ),
        ("fused_costs_census_heuristic", census, 3, true),
        ("fused_costs_census_heuristic_256_bit", census, 3, false),
    ] {
        let spec = fuse::volume::CostSpec { pixel, block_radius_px };
        let prepared = fuse::volume::PreparedProblem::new(&problem, spec, fuse::fusion::Fusion::Heuristic)
            .unwrap_or_else(|e| panic!("{e}"));
        group.bench_function(name, |b| {
            use rayon::prelude::*;
            let (height, band) = (
                problem.reference.height,
                fuse::volume::band_rows(problem.reference.height),
            );
            fuse::wide::set_enabled(wide);
            b.iter(|| {
                let firsts: u32 = (0..height.div_ceil(band))
                    .into_par_iter()
                    .map_init(fuse::volume::BandScratch::default, |buffers, index| {
                        let mut first = 0u32;
                        let rows = index * band..((index + 1) * band).min(height);
                        prepared.fused_band_with(rows, buffers, &mut |_, _, costs| {
                            first = first.wrapping_add(u32::from(costs[0]));
                        });
                        first
                    })
                    .sum();
                black_box(firsts)
            });
            fuse::wide::set_enabled(true);
        });
    }
    group.finish();
}

/// The hot shapes of MFuseNet (a 32 × 96 × 128 volume): the k7 8→4 convolution, its two
/// gradients, and the whole three-view forward pass with cost volumes (`mfusenet` on a 128×96 set).
fn mfusenet(c: &mut Criterion) {
    use fuse::nn::Tensor;
    use fuse::nn::conv::{
        ConvInput, Epilogue, conv3d_accumulate_input, conv3d_input, conv3d_same, conv3d_same_input_grad,
        conv3d_same_weight_grad, input_channels,
    };
    let shape = [8, 32, 96, 128];
    let x = Tensor {
        shape,
        data: (0..shape.iter().product::<usize>())
            .map(|i| ((i * 7919) % 97) as f32 / 97.0)
            .collect(),
    };
    let weight: Vec<f32> = (0..4 * 8 * 343)
        .map(|i| ((i * 31) % 17) as f32 / 170.0 - 0.05)
        .collect();
    let grad = conv3d_same(&x, &weight, 4, 7, None);
    let mut group = c.benchmark_group("mfusenet_32x96x128");
    group.sample_size(10);
    group.bench_function("conv_k7_8to4_forward", |b| {
        b.iter(|| black_box(conv3d_same(&x, &weight, 4, 7, None)))
    });
    // The same on the 256-bit paths, where the host would take the 512-bit kernel
    // (`fuse::wide`; the same bits either way).
    group.bench_function("conv_k7_8to4_forward_256_bit", |b| {
        fuse::wide::set_enabled(false);
        b.iter(|| black_box(conv3d_same(&x, &weight, 4, 7, None)));
        fuse::wide::set_enabled(true);
    });
    // In 16-bit integer products (`fuse::nn::int16_kernel`, AVX2), against the 256-bit f32 path.
    group.bench_function("conv_k7_8to4_forward_int16", |b| {
        fuse::nn::conv::with_precision(fuse::nn::conv::Precision::Int16, || {
            b.iter(|| black_box(conv3d_same(&x, &weight, 4, 7, None)))
        })
    });
    // The lite network's commonest layer: 3³, 4 → 4 channels.
    let x4 = Tensor {
        shape: [4, shape[1], shape[2], shape[3]],
        data: x.data[..x.data.len() / 2].to_vec(),
    };
    let weight3: Vec<f32> = (0..4 * 4 * 27).map(|i| ((i * 31) % 17) as f32 / 170.0 - 0.05).collect();
    group.bench_function("conv_k3_4to4_forward", |b| {
        b.iter(|| black_box(conv3d_same(&x4, &weight3, 4, 3, None)))
    });
    // The stride-2 transposed layer (`up2`, 4 → 4 channels) on a half-size input: by output
    // parity (`fuse::nn::transposed`, inference's path) against the "same" convolution of the
    // zero-upsampled input (training's form, inference's before).
    let small = Tensor {
        shape: [4, shape[1] / 2, shape[2] / 2, shape[3] / 2],
        data: x4.data[..x4.data.len() / 8].to_vec(),
    };
    let up_weight = fuse::nn::conv::transposed_as_conv(&weight3, 4, 4);
    group.bench_function("conv_transpose_4to4_forward_parity", |b| {
        b.iter(|| {
            black_box(fuse::nn::transposed::transposed_conv3d_eval(
                &small, &up_weight, 4, None, true,
            ))
        })
    });
    group.bench_function("conv_transpose_4to4_forward_zero_upsampled", |b| {
        b.iter(|| {
            let up = small.upsample2_zeros([2 * small.shape[1], 2 * small.shape[2], 2 * small.shape[3]]);
            black_box(conv3d_same(&up, &up_weight, 4, 3, None))
        })
    });
    group.bench_function("conv_k3_4to4_forward_256_bit", |b| {
        fuse::wide::set_enabled(false);
        b.iter(|| black_box(conv3d_same(&x4, &weight3, 4, 3, None)));
        fuse::wide::set_enabled(true);
    });
    group.bench_function("conv_k3_4to4_forward_int16", |b| {
        fuse::nn::conv::with_precision(fuse::nn::conv::Precision::Int16, || {
            b.iter(|| black_box(conv3d_same(&x4, &weight3, 4, 3, None)))
        })
    });
    // In bfloat16 products (`fuse::nn::bf16_kernel`, where the host has AVX512-BF16; f32
    // elsewhere): channel pairs at an even input count, the 7³ layer, the 3³ one and the 3³
    // concatenation of four views' 4 channels.
    let bf16 = |x: &Tensor, weight: &[f32], k: usize| {
        fuse::nn::conv::with_precision(fuse::nn::conv::Precision::Bf16, || conv3d_same(x, weight, 4, k, None))
    };
    group.bench_function("conv_k7_8to4_forward_bf16", |b| {
        b.iter(|| black_box(bf16(&x, &weight, 7)))
    });
    group.bench_function("conv_k3_4to4_forward_bf16", |b| {
        b.iter(|| black_box(bf16(&x4, &weight3, 3)))
    });
    let x16 = Tensor {
        shape: [16, shape[1], shape[2], shape[3]],
        data: x.data.iter().chain(&x.data).copied().collect(),
    };
    let weight16: Vec<f32> = (0..4 * 16 * 27)
        .map(|i| ((i * 31) % 17) as f32 / 170.0 - 0.05)
        .collect();
    group.bench_function("conv_k3_16to4_forward_bf16", |b| {
        b.iter(|| black_box(bf16(&x16, &weight16, 3)))
    });
    group.bench_function("conv_k7_8to4_input_grad", |b| {
        b.iter(|| black_box(conv3d_same_input_grad(&grad, &weight, 8, 7)))
    });
    group.bench_function("conv_k7_8to4_weight_grad", |b| {
        b.iter(|| black_box(conv3d_same_weight_grad(&x, &grad, 7)))
    });
    // The same 8 → 4 layer as two groups of 4 input channels, each added in (inference's
    // `concat` a view at a time; the copies of the halves are part of what it costs here).
    let half = |g: usize| -> (Tensor, Vec<f32>) {
        let plane = shape[1] * shape[2] * shape[3];
        let part = Tensor {
            shape: [4, shape[1], shape[2], shape[3]],
            data: x.data[4 * g * plane..4 * (g + 1) * plane].to_vec(),
        };
        let own = input_channels(&weight, 4, 8, 7, 4 * g..4 * (g + 1));
        (part, own)
    };
    group.bench_function("conv_k7_8to4_forward_two_groups", |b| {
        b.iter(|| {
            let (first, own) = half(0);
            let sum = conv3d_input(ConvInput::Owned(first), &own, 4, 7, None, Epilogue::default());
            let (second, own) = half(1);
            black_box(conv3d_accumulate_input(ConvInput::Owned(second), &own, 7, sum, true))
        })
    });
    let three_view = Problem {
        neighbours: problem(128, 96, 32).neighbours.into_iter().take(2).collect(),
        ..problem(128, 96, 32)
    };
    let method = fuse::methods::build("mfusenet", None).unwrap_or_else(|e| panic!("{e}"));
    group.bench_function("mfusenet_three_view_128x96", |b| {
        b.iter(|| black_box(method.run(&three_view, &|_| {})))
    });
    group.finish();
}

/// Graph cuts on a 160×120 slanted plane with 32 num_disparities: stereo against three and five
/// views (the cuts dominate), and the max-flow alone on a 4-connected grid with random terminals.
fn graph_cuts(c: &mut Criterion) {
    let five = problem(160, 120, 32);
    let three = Problem {
        neighbours: five.neighbours.iter().take(2).cloned().collect(),
        ..five.clone()
    };
    let mut group = c.benchmark_group("graph_cuts_160x120x32");
    group.sample_size(10);
    for (name, problem) in [
        ("gc-stereo", &three),
        ("gc-heuristic", &three),
        ("gc-heuristic-five", &five),
    ] {
        let method = fuse::methods::build(name.trim_end_matches("-five"), None).unwrap_or_else(|e| panic!("{e}"));
        group.bench_function(name, |b| b.iter(|| black_box(method.run(problem, &|_| {}))));
    }
    group.bench_function("maxflow_grid_256x256", |b| {
        b.iter(|| {
            let mut graph = fuse::maxflow::Graph::new();
            let side = 256u32;
            for i in 0..side * side {
                let node = graph.add_node();
                let t = i64::from((i * 7919) % 41) - 20;
                graph.add_terminal_weights(node, t.max(0), (-t).max(0));
            }
            for y in 0..side {
                for x in 0..side {
                    let i = y * side + x;
                    if x + 1 < side {
                        graph.add_edge(i, i + 1, 6, 6);
                    }
                    if y + 1 < side {
                        graph.add_edge(i, i + side, 6, 6);
                    }
                }
            }
            black_box(graph.max_flow())
        })
    });
    group.finish();
}

/// The winner-take-all with its peak-ratio confidence on one band of fused costs (1920 pixels ×
/// 128 disparities, what block matching reads per image row), against the winners alone: the
/// confidence's share of the readout.
fn winners(c: &mut Criterion) {
    let (pixels, nd) = (1920, 128);
    let costs: Vec<u16> = (0..pixels * nd)
        .map(|i| ((i * 2_654_435_761) % 4000) as u16 + if i % nd == (i / nd) % nd { 0 } else { 500 })
        .collect();
    let mut out = vec![0.0f32; pixels];
    let mut confidence = vec![0.0f32; pixels];
    let mut group = c.benchmark_group("winners_1920x128");
    group.bench_function("winners", |b| {
        b.iter(|| fuse::wta::winner_take_all(black_box(&costs), nd, 0, None, &mut out))
    });
    group.bench_function("winners_with_confidence", |b| {
        b.iter(|| fuse::wta::winner_take_all_confident(black_box(&costs), nd, 0, None, &mut out, &mut confidence))
    });
    group.finish();
}

/// The pixel costs of one reference row against a neighbour's search lines (1920 columns, 128
/// disparities, the hot loop of block matching at 1080p): Birchfield–Tomasi on colour (the
/// channels' halves summed in bytes) against absolute differences on colour (the channels' exact
/// mean, in 16-bit lanes, the Birchfield–Tomasi colour cost's arithmetic before), census 7×7 (48
/// bits), its centre-symmetric form and census 5×5 (24 bits each).
fn pixel_costs(c: &mut Criterion) {
    use fuse::cost::{PixelCost, PreparedView};
    use fuse::lines::{SearchLines, pixel_cost_tile_lines};
    let (width, nd) = (1920, 128);
    let problem = problem(width, 16, nd);
    let neighbour = &problem.neighbours[1];
    let mut out = vec![0u8; width * nd];
    let mut group = c.benchmark_group("pixel_costs_1920x128");
    for (name, cost) in [
        ("birchfield_tomasi_colour", PixelCost::BirchfieldTomasi),
        ("absolute_difference_colour", PixelCost::AbsoluteDifference),
        (
            "census_7x7",
            PixelCost::Census {
                radius: 3,
                symmetric: false,
            },
        ),
        (
            "census_7x7_symmetric",
            PixelCost::Census {
                radius: 3,
                symmetric: true,
            },
        ),
        (
            "census_5x5",
            PixelCost::Census {
                radius: 2,
                symmetric: false,
            },
        ),
    ] {
        let reference = PreparedView::new(problem.reference.clone(), cost);
        let Some(lines) = SearchLines::new(&neighbour.image, cost, neighbour.offset, 0..nd as i32) else {
            panic!("an axis neighbour has search lines");
        };
        group.bench_function(name, |b| {
            b.iter(|| {
                pixel_cost_tile_lines(cost, &reference, &lines, 8, 0..width as isize, 0, nd, &mut out);
                black_box(&out);
            })
        });
    }
    group.finish();
    // The access pattern inside the fused tiles: one 104-column tile (96 and the block's halo)
    // row after row down 256 rows, for a neighbour along the row (its search lines are the
    // image rows) and one along the column (a line per column: the tile reads 104 lines).
    let (height, tile) = (256, 104);
    let problem = self::problem(width, height, nd);
    let cost = PixelCost::Census {
        radius: 3,
        symmetric: false,
    };
    let reference = PreparedView::new(problem.reference.clone(), cost);
    let mut out = vec![0u8; tile * nd];
    let mut group = c.benchmark_group("census_7x7_tile_104x256x128");
    for (name, neighbour) in [("right", &problem.neighbours[1]), ("bottom", &problem.neighbours[3])] {
        let Some(lines) = SearchLines::new(&neighbour.image, cost, neighbour.offset, 0..nd as i32) else {
            panic!("an axis neighbour has search lines");
        };
        group.bench_function(name, |b| {
            b.iter(|| {
                for y in 0..height {
                    pixel_cost_tile_lines(cost, &reference, &lines, y, 900..900 + tile as isize, 0, nd, &mut out);
                    black_box(&out);
                }
            })
        });
    }
    group.finish();
}

/// An estimate of 20 px everywhere: every pixel is tested by the post-processing benched.
fn flat_estimate(width: usize, height: usize) -> fuse::DisparityImage {
    fuse::DisparityImage {
        width,
        height,
        data: vec![20.0; width * height],
        confidence: None,
    }
}

/// MFuseNet's last steps: the thin-part recovery on each pixel's own costs and over cross-shaped
/// supports (the default), from a flat estimate (every pixel is tested).
fn thin_parts(c: &mut Criterion) {
    use fuse::thin_parts::{ThinParts, recover_thin_parts};
    let problem = problem(640, 360, 64);
    let flat = flat_estimate(640, 360);
    let mut group = c.benchmark_group("thin_parts_640x360x64");
    group.sample_size(10);
    let own = ThinParts {
        cross_support: None,
        ..ThinParts::default()
    };
    for (name, config) in [("own_costs", own), ("cross_support", ThinParts::default())] {
        group.bench_function(name, |b| {
            b.iter(|| {
                let mut disparity = flat.clone();
                black_box(recover_thin_parts(&problem, &mut disparity, &config))
            })
        });
    }
    group.finish();
}

/// MFuseNet's last step: the photometric refinement (two Gauss–Newton steps, 15 × 15 windows) of
/// a five-view 640×360 set from a flat estimate.
fn photometric(c: &mut Criterion) {
    use fuse::photometric::{Photometric, refine_photometric};
    let problem = problem(640, 360, 64);
    let flat = flat_estimate(640, 360);
    let mut group = c.benchmark_group("photometric_640x360");
    group.sample_size(10);
    group.bench_function("five_views", |b| {
        b.iter(|| {
            let mut disparity = flat.clone();
            black_box(refine_photometric(&problem, &mut disparity, &Photometric::default()))
        })
    });
    group.finish();
}

/// MFuseNet's weighted median with votes (its defaults: an 11 × 11 window at step 2) on the
/// slanted plane's disparities with a little noise (so that the windows' values spread over
/// bins, as a network's sub-pixel answers do) and a quarter of the votes low.
fn weighted_median(c: &mut Criterion) {
    use fuse::postprocess::{WeightedMedian, weighted_median_with_votes};
    let (width, height) = (640, 360);
    let problem = problem(width, height, 64);
    let noise = |i: usize| ((i as f64 * 12.9898).sin() * 43758.5453).fract() as f32 * 0.25;
    let disparity = fuse::DisparityImage {
        width,
        height,
        data: (0..width * height)
            .map(|i| 8.0 + 40.0 * (i % width) as f32 / width as f32 + noise(i))
            .collect(),
        confidence: None,
    };
    let votes: Vec<f32> = (0..width * height)
        .map(|i| if i % 4 == 0 { 0.05 } else { 1.0 })
        .collect();
    let mut group = c.benchmark_group("weighted_median_640x360");
    group.sample_size(20);
    group.bench_function("with_votes", |b| {
        b.iter(|| {
            black_box(weighted_median_with_votes(
                &disparity,
                &problem.reference,
                &WeightedMedian::default(),
                Some(&votes),
            ))
        })
    });
    group.finish();
}

criterion_group!(
    benches,
    weighted_median,
    methods,
    mfusenet,
    graph_cuts,
    winners,
    pixel_costs,
    thin_parts,
    photometric
);
criterion_main!(benches);
