//! MFuseNet (paper, section IV): a small 3D CNN that takes one cost volume per neighbour view
//! and returns the disparity by soft-argmin.
//!
//! - [`network`]: the layers and their wiring, eval (BatchNorm folded) and train mode with the
//!   backward pass, PyTorch's parameter names.
//! - [`weights`]: safetensors files with the reference `state_dict`'s names and shapes.
//! - [`pyramid`]: coarse to fine for ranges wider than the networks were trained on.

pub mod infer;
pub mod input;
pub mod network;
pub mod pyramid;
pub mod train;
pub mod weights;

pub use network::{Architecture, Network};
pub use weights::WeightsInfo;

/// Errors of the network and its weight files; each names the file and tensor or the shape.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// The network got another number of cost volumes than it was built for.
    #[error("the network takes {}, got {got}", views_text(*expected))]
    InputCount {
        /// Views of the network.
        expected: usize,
        /// Volumes given.
        got: usize,
    },
    /// A cost volume is not `[1, D, H, W]` with D, H, W multiples of 4, or differs from the others.
    #[error("cost volume of shape {shape:?}: expected [1, D, H, W], all alike, D, H, W multiples of 4")]
    InputShape {
        /// The shape given.
        shape: [usize; 4],
    },
    /// A metadata entry inference reads has a bad value.
    #[error("weights file {file}: metadata {key} = {value:?}, expected {expected}")]
    Metadata {
        /// File.
        file: String,
        /// The metadata key.
        key: &'static str,
        /// Its value.
        value: String,
        /// What it should be.
        expected: &'static str,
    },
    /// The slices kept out of the estimate leave none to read it from.
    #[error(
        "{context_below} context slices below the searched range leave none of the volume's {num_disparities} disparities"
    )]
    ContextBelow {
        /// Slices left out of the estimate.
        context_below: usize,
        /// Slices in the volumes.
        num_disparities: usize,
    },
    /// Test-time flips were asked for volumes whose neighbours have no mirror image among
    /// themselves (or that are not single neighbours' volumes).
    #[error("test-time flips need neighbours that a mirror maps onto each other; these sit at {offsets:?}")]
    NoMirror {
        /// The neighbours' grid offsets (empty when a volume is not one neighbour's).
        offsets: Vec<[i32; 2]>,
    },
    /// A weights file cannot be read.
    #[error("cannot read weights file {file}: {reason}")]
    Read {
        /// File.
        file: String,
        /// Why.
        reason: String,
    },
    /// A weights file cannot be written.
    #[error("cannot write weights file {file}: {reason}")]
    Write {
        /// File.
        file: String,
        /// Why.
        reason: String,
    },
    /// Not a safetensors file (truncated, bad header).
    #[error("weights file {file} is not a valid safetensors file: {reason}")]
    Format {
        /// File.
        file: String,
        /// The parser's words.
        reason: String,
    },
    /// A tensor of the model is missing.
    #[error("weights file {file} has no tensor '{tensor}'")]
    MissingTensor {
        /// File.
        file: String,
        /// Tensor name.
        tensor: String,
    },
    /// A tensor that is not the model's.
    #[error("weights file {file} has tensor '{tensor}', which is not in the MFuseNet state_dict")]
    UnexpectedTensor {
        /// File.
        file: String,
        /// Tensor name.
        tensor: String,
    },
    /// A tensor has the wrong shape.
    #[error("weights file {file}: tensor '{tensor}' has shape {got:?}, expected {expected}")]
    TensorShape {
        /// File.
        file: String,
        /// Tensor name.
        tensor: String,
        /// Expected shape.
        expected: String,
        /// Shape found.
        got: Vec<usize>,
    },
    /// A tensor has a type we do not read.
    #[error("weights file {file}: tensor '{tensor}' is {dtype} (expected F32 or F64; I64 for num_batches_tracked)")]
    TensorDtype {
        /// File.
        file: String,
        /// Tensor name.
        tensor: String,
        /// Type found.
        dtype: String,
    },
    /// A NaN or infinite value (or a negative running variance).
    #[error(
        "weights file {file}: tensor '{tensor}' has an invalid value (NaN, infinite or negative variance) at index {index}"
    )]
    NonFinite {
        /// File.
        file: String,
        /// Tensor name.
        tensor: String,
        /// Flat index of the first bad value.
        index: usize,
    },
    /// The file is for another number of views.
    #[error(
        "weights file {file} is for {} (concat.0.weight), the method needs {}",
        views_text(*got),
        views_text(*expected)
    )]
    Variant {
        /// File.
        file: String,
        /// Views needed.
        expected: usize,
        /// Views of the file.
        got: usize,
    },
    /// The file was trained on inputs normalised otherwise than ours.
    #[error(
        "weights file {file} was trained on inputs in steps of 1/{got} (metadata input_steps_per_unit), these inputs are in steps of 1/{expected}"
    )]
    Normalisation {
        /// File.
        file: String,
        /// Steps per unit of our inputs.
        expected: f32,
        /// Steps per unit in the file's metadata.
        got: String,
    },
    /// The metadata's `estimate` is neither `soft-argmin` nor `refine`.
    #[error("weights file {file}: metadata estimate = {value:?}, expected \"soft-argmin\" or \"refine\"")]
    Estimate {
        /// File.
        file: String,
        /// The metadata's value.
        value: String,
    },
}

/// A network's inputs in words: `0` is the view-count-agnostic network's "any number".
fn views_text(views: usize) -> String {
    match views {
        0 => format!(
            "1 to {} cost volumes (view-count-agnostic, views pooled by mean and maximum)",
            crate::nn::pool::MAX_VIEWS
        ),
        1 => "1 cost volume".to_owned(),
        n => format!("{n} cost volumes"),
    }
}

#[cfg(test)]
mod fixtures;

#[cfg(test)]
mod tests {
    use super::Error;

    #[test]
    fn a_pooled_file_is_named_in_words_not_as_zero_views() {
        let message = Error::Variant {
            file: "any.safetensors".into(),
            expected: 4,
            got: 0,
        }
        .to_string();
        assert!(
            message.contains("view-count-agnostic") && message.contains("needs 4 cost volumes"),
            "{message}"
        );
        let message = Error::InputCount { expected: 0, got: 0 }.to_string();
        assert!(message.starts_with("the network takes 1 to "), "{message}");
    }
}
