//! Order-invariant pooling across views: the feature volumes `[C, D, H, W]` of any number of
//! views become one `[2C, D, H, W]`, their mean (channels `0..C`) and their maximum (channels
//! `C..2C`). A fusion layer that reads this instead of the views' features side by side (the
//! paper's `concat`, `4N → 4` channels) takes any number of views in any order: the building
//! block of a view-count-agnostic MFuseNet.
//!
//! Every view must have the shape of the first (the network checks its inputs); views beyond
//! [`MAX_VIEWS`] are not pooled.

use super::Tensor;

/// The most views a pooling takes (the maximum's view index is kept as a `u16`).
pub const MAX_VIEWS: usize = u16::MAX as usize;

/// The mean and the maximum across `views`: `[2C, D, H, W]`, the mean's channels first. No views
/// give an empty tensor.
pub fn mean_max(views: &[Tensor]) -> Tensor {
    pool(views, None)
}

/// [`mean_max`] and, for [`mean_max_backward`], which view gave each maximum (the first of equal
/// ones), one index per value of a view.
pub fn mean_max_train(views: &[Tensor]) -> (Tensor, Vec<u16>) {
    let mut argmax = Vec::new();
    let pooled = pool(views, Some(&mut argmax));
    (pooled, argmax)
}

fn pool(views: &[Tensor], mut argmax: Option<&mut Vec<u16>>) -> Tensor {
    let views = &views[..views.len().min(MAX_VIEWS)];
    let Some(first) = views.first() else {
        return Tensor::zeros([0; 4]);
    };
    let [c, d, h, w] = first.shape;
    let n = first.data.len();
    let mut out = Tensor::zeros([2 * c, d, h, w]);
    let (mean, max) = out.data.split_at_mut(n);
    mean.copy_from_slice(&first.data);
    max.copy_from_slice(&first.data);
    if let Some(argmax) = argmax.as_deref_mut() {
        argmax.clear();
        argmax.resize(n, 0);
    }
    for (v, view) in views.iter().enumerate().skip(1) {
        for (s, x) in mean.iter_mut().zip(&view.data) {
            *s += x;
        }
        match argmax.as_deref_mut() {
            Some(argmax) => {
                for ((m, a), x) in max.iter_mut().zip(argmax.iter_mut()).zip(&view.data) {
                    if *x > *m {
                        *m = *x;
                        *a = v as u16;
                    }
                }
            }
            None => {
                for (m, x) in max.iter_mut().zip(&view.data) {
                    *m = m.max(*x);
                }
            }
        }
    }
    let scale = 1.0 / views.len() as f32;
    for s in mean.iter_mut() {
        *s *= scale;
    }
    out
}

/// The gradient of each of `views` views given the pooled output's gradient `grad` (`[2C, D, H,
/// W]`) and [`mean_max_train`]'s `argmax`: the mean's share `1/views` to every view, the
/// maximum's whole to the view that gave it.
pub fn mean_max_backward(grad: &Tensor, argmax: &[u16], views: usize) -> Vec<Tensor> {
    let [c2, d, h, w] = grad.shape;
    let shape = [c2 / 2, d, h, w];
    let n = shape.iter().product::<usize>();
    let (mean, max) = grad.data.split_at(n.min(grad.data.len()));
    let scale = 1.0 / views.max(1) as f32;
    (0..views.min(MAX_VIEWS))
        .map(|v| {
            let mut out = Tensor::zeros(shape);
            for (((o, g_mean), g_max), a) in out.data.iter_mut().zip(mean).zip(max).zip(argmax) {
                *o = g_mean * scale + if usize::from(*a) == v { *g_max } else { 0.0 };
            }
            out
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    fn random(shape: [usize; 4], rng: &mut SplitMix64) -> Tensor {
        let mut t = Tensor::zeros(shape);
        for v in &mut t.data {
            *v = rng.uniform_f32(-1.0, 1.0);
        }
        t
    }

    #[test]
    fn pooling_matches_the_plain_loops_and_ignores_the_order_of_the_views() {
        let mut rng = SplitMix64::new(7);
        let shape = [4, 3, 5, 6];
        for count in [1, 2, 3, 5, 9] {
            let views: Vec<Tensor> = (0..count).map(|_| random(shape, &mut rng)).collect();
            let pooled = mean_max(&views);
            let (trained, argmax) = mean_max_train(&views);
            assert_eq!(pooled, trained, "{count} views: the eval and train passes agree");
            let reference = crate::nn::reference::mean_max(&views);
            assert_eq!(pooled.shape, [8, 3, 5, 6]);
            for (i, (a, b)) in pooled.data.iter().zip(&reference.data).enumerate() {
                assert!((a - b).abs() <= 1e-6, "{count} views, value {i}: {a} vs {b}");
            }
            for (i, a) in argmax.iter().enumerate() {
                assert_eq!(views[usize::from(*a)].data[i], pooled.data[pooled.data.len() / 2 + i]);
            }
            let mut reversed = views.clone();
            reversed.reverse();
            let again = mean_max(&reversed);
            for (a, b) in pooled.data.iter().zip(&again.data) {
                assert!((a - b).abs() <= 1e-6, "{count} views: order changed the pooling");
            }
        }
        assert_eq!(mean_max(&[]).data.len(), 0);
    }

    #[test]
    fn backward_matches_finite_differences() {
        // loss = Σ g ⊙ mean_max(views): each input's gradient by central differences.
        let mut rng = SplitMix64::new(11);
        let shape = [2, 2, 3, 4];
        let views: Vec<Tensor> = (0..3).map(|_| random(shape, &mut rng)).collect();
        let (pooled, argmax) = mean_max_train(&views);
        let g = random(pooled.shape, &mut rng);
        let grads = mean_max_backward(&g, &argmax, views.len());
        assert_eq!(grads.len(), 3);
        let loss = |views: &[Tensor]| -> f64 {
            let out = mean_max(views);
            out.data
                .iter()
                .zip(&g.data)
                .map(|(o, g)| f64::from(*o) * f64::from(*g))
                .sum()
        };
        let eps = 1e-3f32;
        let mut checked = 0;
        for v in 0..views.len() {
            for i in 0..views[v].data.len() {
                // Where two views' values are within the step the maximum is not differentiable.
                let mut values: Vec<f32> = views.iter().map(|view| view.data[i]).collect();
                values.sort_by(|a, b| b.total_cmp(a));
                if values[0] - values[1] < 4.0 * eps {
                    continue;
                }
                let mut plus = views.clone();
                plus[v].data[i] += eps;
                let mut minus = views.clone();
                minus[v].data[i] -= eps;
                let numeric = (loss(&plus) - loss(&minus)) / (2.0 * f64::from(eps));
                let analytic = f64::from(grads[v].data[i]);
                assert!(
                    (numeric - analytic).abs() < 1e-3,
                    "view {v}, value {i}: numeric {numeric}, analytic {analytic}"
                );
                checked += 1;
            }
        }
        assert!(checked >= 120, "only {checked} of 144 values checked");
    }
}
