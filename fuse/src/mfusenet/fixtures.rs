//! The reference network's own results (`../shared/fixtures/mfusenet/n{1,2,4}.safetensors`,
//! PyTorch float64 with seeded weights and non-trivial BatchNorm statistics) matched by ours:
//! eval-mode logits and disparity, train-mode disparity, loss, every parameter's gradient and the
//! updated running statistics.

use std::path::PathBuf;

use safetensors::tensor::{Dtype, SafeTensors};

use super::network::Network;
use super::weights;
use crate::nn::Tensor;
use crate::nn::regression::soft_argmin;

fn fixture(views: usize) -> Vec<u8> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/fixtures/mfusenet")
        .join(format!("n{views}.safetensors"));
    std::fs::read(&path).unwrap_or_else(|e| {
        panic!(
            "missing test fixture {} ({e}): the MFuseNet reference results live in ../shared/fixtures beside the repository",
            path.display()
        )
    })
}

fn floats(tensors: &SafeTensors<'_>, name: &str) -> (Vec<usize>, Vec<f64>) {
    let view = tensors.tensor(name).unwrap_or_else(|e| panic!("{name}: {e}"));
    let values = match view.dtype() {
        Dtype::F64 => view
            .data()
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
            .collect(),
        Dtype::U8 => view.data().iter().map(|b| f64::from(*b)).collect(),
        other => panic!("{name}: {other:?}"),
    };
    (view.shape().to_vec(), values)
}

/// Largest |got − expected| over the largest |expected| (a scale-free error for tensors whose
/// entries span orders of magnitude).
fn relative_error(got: &[f32], expected: &[f64]) -> f64 {
    assert_eq!(got.len(), expected.len());
    let scale = expected.iter().fold(0f64, |m, v| m.max(v.abs())).max(1e-12);
    got.iter()
        .zip(expected)
        .fold(0f64, |m, (a, b)| m.max((f64::from(*a) - b).abs()))
        / scale
}

fn check(views: usize, parameters: usize) {
    let bytes = fixture(views);
    let tensors = SafeTensors::deserialize(&bytes).unwrap_or_else(|e| panic!("{e}"));
    let (net, _) = weights::from_bytes(&bytes, "fixture", "param.", Some(views)).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(net.parameter_count(), parameters);
    let inputs: Vec<Tensor> = (0..views)
        .map(|i| {
            let (shape, values) = floats(&tensors, &format!("input.{i}"));
            Tensor {
                shape: [shape[0], shape[1], shape[2], shape[3]],
                data: values.iter().map(|v| *v as f32).collect(),
            }
        })
        .collect();

    let logits = net.logits(&inputs).unwrap_or_else(|e| panic!("{e}"));
    let error = relative_error(&logits.data, &floats(&tensors, "logits.eval").1);
    assert!(error < 1e-4, "N={views} eval logits: relative error {error:e}");
    let (disparity, _) = soft_argmin(&logits);
    let error = relative_error(&disparity, &floats(&tensors, "output.eval").1);
    assert!(error < 1e-4, "N={views} eval disparity: relative error {error:e}");

    let mut train = net.clone();
    let target: Vec<f32> = floats(&tensors, "target").1.iter().map(|v| *v as f32).collect();
    let mask: Vec<bool> = floats(&tensors, "mask").1.iter().map(|v| *v != 0.0).collect();
    let (loss, disparity, gradients) = train
        .loss_and_gradients(&inputs, &target, &mask)
        .unwrap_or_else(|e| panic!("{e}"));
    let error = relative_error(&disparity, &floats(&tensors, "output.train").1);
    assert!(error < 1e-4, "N={views} train disparity: relative error {error:e}");
    let expected_loss = floats(&tensors, "loss.train").1[0];
    assert!(
        (f64::from(loss) - expected_loss).abs() < 1e-5 * expected_loss.abs().max(1.0),
        "N={views} loss {loss} vs {expected_loss}"
    );
    assert_eq!(gradients.tensors.len(), 15 * 3 + 2);
    for (name, grad) in &gradients.tensors {
        let (shape, expected) = floats(&tensors, &format!("grad.{name}"));
        assert_eq!(grad.len(), shape.iter().product::<usize>(), "{name}");
        if expected.iter().all(|v| v.abs() < 1e-9) {
            // classify.bias: a constant shift of the logits leaves the softmax unchanged, so its
            // gradient is zero up to rounding.
            assert!(
                grad.iter().all(|v| v.abs() < 1e-5),
                "N={views} grad.{name}: {grad:?} should be 0"
            );
            continue;
        }
        let error = relative_error(grad, &expected);
        assert!(error < 1e-3, "N={views} grad.{name}: relative error {error:e}");
    }
    for layer in train.layers() {
        for (field, values) in [
            ("running_mean", &layer.bn.running_mean),
            ("running_var", &layer.bn.running_var),
        ] {
            let name = format!("after_train.{}.1.{field}", layer.name);
            let error = relative_error(values, &floats(&tensors, &name).1);
            assert!(error < 1e-4, "N={views} {name}: relative error {error:e}");
        }
    }
    // The shared feature tower counts one pass per view.
    let before = net.feature[0].bn.num_batches_tracked;
    assert_eq!(train.feature[0].bn.num_batches_tracked, before + views as i64);
    assert_eq!(
        train.fuse[0].bn.num_batches_tracked,
        net.fuse[0].bn.num_batches_tracked + 1
    );
}

#[test]
fn stereo_network_matches_the_pytorch_reference() {
    check(1, 33_441);
}

#[test]
fn three_view_network_matches_the_pytorch_reference() {
    check(2, 38_929);
}

#[test]
fn five_view_network_matches_the_pytorch_reference() {
    check(4, 49_905);
}

#[test]
fn saved_weights_read_back_identically() {
    let bytes = fixture(2);
    let (net, _) = weights::from_bytes(&bytes, "fixture", "param.", Some(2)).unwrap_or_else(|e| panic!("{e}"));
    let mut info = super::WeightsInfo::default();
    info.set("variant", "mfusenet");
    let saved = weights::to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}"));
    let (again, info_again) = weights::from_bytes(&saved, "saved", "", None).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(again, net);
    assert_eq!(info_again.get("variant"), Some("mfusenet"));
    let names: Vec<String> = weights::state_dict_shapes(2).into_iter().map(|(n, _)| n).collect();
    assert_eq!(names.len(), 15 * 6 + 2);
    let _ = Network::zeros(2);
}
