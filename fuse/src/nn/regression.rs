//! The network's head: softmax over the disparity axis and its expectation (soft-argmin as the
//! paper and the reference implementation write it: the softmax of the logits themselves, not of
//! their negation), and the smooth-L1 training loss.

use super::Tensor;

/// Disparity per pixel `Σ_d d · softmax_d(logits)` of `[1, D, H, W]` logits, and the
/// probabilities (for the backward pass). Returns `([H·W] disparities, probabilities)`.
pub fn soft_argmin(logits: &Tensor) -> (Vec<f32>, Tensor) {
    let [_, d, h, w] = logits.shape;
    let plane = h * w;
    let mut probabilities = Tensor::zeros(logits.shape);
    let mut disparity = vec![0f32; plane];
    for (pixel, out) in disparity.iter_mut().enumerate() {
        let max = (0..d)
            .map(|z| logits.data[z * plane + pixel])
            .fold(f32::NEG_INFINITY, f32::max);
        let mut sum = 0f64;
        for z in 0..d {
            let e = (logits.data[z * plane + pixel] - max).exp();
            probabilities.data[z * plane + pixel] = e;
            sum += f64::from(e);
        }
        let mut expectation = 0f64;
        for z in 0..d {
            let p = (f64::from(probabilities.data[z * plane + pixel]) / sum) as f32;
            probabilities.data[z * plane + pixel] = p;
            expectation += z as f64 * f64::from(p);
        }
        *out = expectation as f32;
    }
    (disparity, probabilities)
}

/// Gradient of the logits given the disparities' gradient: `∂/∂l_d = p_d · (d − disparity)`.
pub fn soft_argmin_backward(grad: &[f32], disparity: &[f32], probabilities: &Tensor) -> Tensor {
    let [_, d, h, w] = probabilities.shape;
    let plane = h * w;
    let mut out = Tensor::zeros(probabilities.shape);
    for z in 0..d {
        for pixel in 0..plane {
            let i = z * plane + pixel;
            out.data[i] = grad[pixel] * probabilities.data[i] * (z as f32 - disparity[pixel]);
        }
    }
    out
}

/// Smooth-L1 (β = 1) between `prediction` and `target` averaged over the pixels where `mask`
/// is true, and its gradient with respect to `prediction`. With no pixel in the mask the loss is
/// 0 and so is the gradient.
pub fn smooth_l1(prediction: &[f32], target: &[f32], mask: &[bool]) -> (f32, Vec<f32>) {
    let count = mask.iter().filter(|m| **m).count();
    let mut grad = vec![0f32; prediction.len()];
    if count == 0 {
        return (0.0, grad);
    }
    let mut loss = 0f64;
    for (i, ((p, t), m)) in prediction.iter().zip(target).zip(mask).enumerate() {
        if !m {
            continue;
        }
        let diff = p - t;
        if diff.abs() < 1.0 {
            loss += 0.5 * f64::from(diff * diff);
            grad[i] = diff / count as f32;
        } else {
            loss += f64::from(diff.abs() - 0.5);
            grad[i] = diff.signum() / count as f32;
        }
    }
    ((loss / count as f64) as f32, grad)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::conv::tests::random;

    #[test]
    fn soft_argmin_gradient_matches_finite_differences() {
        let logits = random([1, 6, 2, 3], 5);
        let upstream = [0.3f32, -1.0, 0.5, 2.0, 0.1, -0.4];
        let value = |l: &Tensor| -> f64 {
            let (d, _) = soft_argmin(l);
            d.iter()
                .zip(&upstream)
                .map(|(a, b)| f64::from(*a) * f64::from(*b))
                .sum()
        };
        let (d, p) = soft_argmin(&logits);
        let g = soft_argmin_backward(&upstream, &d, &p);
        for i in [0, 5, 17, 35] {
            let (mut plus, mut minus) = (logits.clone(), logits.clone());
            plus.data[i] += 1e-3;
            minus.data[i] -= 1e-3;
            let numeric = (value(&plus) - value(&minus)) / 2e-3;
            assert!(
                (numeric - f64::from(g.data[i])).abs() < 1e-3,
                "{i}: {numeric} vs {}",
                g.data[i]
            );
        }
        // A peaked softmax picks its disparity.
        let mut peaked = Tensor::zeros([1, 4, 1, 1]);
        peaked.data[2] = 50.0;
        assert!((soft_argmin(&peaked).0[0] - 2.0).abs() < 1e-6);
    }

    #[test]
    fn smooth_l1_is_quadratic_near_zero_and_linear_beyond() {
        let (loss, grad) = smooth_l1(&[0.5, 3.0, 9.0], &[0.0, 0.0, 0.0], &[true, true, false]);
        assert!((loss - (0.125 + 2.5) / 2.0).abs() < 1e-6);
        assert_eq!(grad, vec![0.25, 0.5, 0.0]);
        assert_eq!(smooth_l1(&[1.0], &[0.0], &[false]).0, 0.0);
    }
}
