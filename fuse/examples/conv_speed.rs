//! GFLOP/s of the forward convolution at each of MFuseNet's layer shapes (Middlebury third size, 32
//! disparities): `cargo run --release -p fuse --example conv_speed`.
use std::time::Instant;
fn main() {
    let (d, h, w) = (32usize, 372usize, 428usize);
    for &(cin, cout, k, name) in &[
        (1usize, 4usize, 7usize, "feat0 k7 1-4"),
        (4, 4, 5, "feat k5 4-4"),
        (4, 4, 3, "k3 4-4"),
        (8, 4, 7, "concat k7 8-4"),
        (4, 1, 3, "classify k3 4-1"),
    ] {
        let x = fuse::nn::Tensor {
            shape: [cin, d, h, w],
            data: (0..cin * d * h * w).map(|i| (i % 17) as f32).collect(),
        };
        let weight = vec![0.01f32; cout * cin * k * k * k];
        let _ = fuse::nn::conv::conv3d_same(&x, &weight, cout, k, None);
        let start = Instant::now();
        let _ = fuse::nn::conv::conv3d_same(&x, &weight, cout, k, None);
        let secs = start.elapsed().as_secs_f64();
        let flops = 2.0 * (d * h * w) as f64 * (cout * cin * k * k * k) as f64;
        println!("{name}: {secs:.3} s {:.1} GFLOP/s", flops / secs / 1e9);
    }
}
