//! Quick timing of one MFuseNet forward pass (random weights) on a Middlebury-third-sized volume.
use std::time::Instant;

use fuse::mfusenet::Network;
use fuse::nn::Tensor;

fn main() {
    let (d, h, w) = (32, 372, 428);
    let views = 2;
    let net = Network::init(views, 1);
    let inputs: Vec<Tensor> = (0..views)
        .map(|v| Tensor {
            shape: [1, d, h, w],
            data: (0..d * h * w)
                .map(|i| ((i * 7 + v * 13) % 101) as f32 / 101.0)
                .collect(),
        })
        .collect();
    for _ in 0..2 {
        let start = Instant::now();
        let logits = net.logits(&inputs).unwrap_or_else(|e| panic!("{e}"));
        println!("forward {:.2} s ({:?})", start.elapsed().as_secs_f64(), logits.shape);
    }
    let x = Tensor {
        shape: [8, d, h, w],
        data: (0..8 * d * h * w).map(|i| (i % 17) as f32).collect(),
    };
    let weight = vec![0.01f32; 4 * 8 * 343];
    let start = Instant::now();
    let _ = fuse::nn::conv::conv3d_same(&x, &weight, 4, 7, None);
    let secs = start.elapsed().as_secs_f64();
    let flops = 2.0 * (d * h * w) as f64 * 4.0 * 8.0 * 343.0;
    println!("conv k7 8->4: {secs:.2} s, {:.1} GFLOP/s", flops / secs / 1e9);
}
