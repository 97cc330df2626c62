//! Weights as safetensors files whose tensor names and shapes are the reference model's
//! `state_dict` (`feature.0.0.weight`, `feature.0.1.running_var`, `concat.0.weight`,
//! `up1.0.weight` as `[cin, cout, 3, 3, 3]`, `classify.bias`, …), so that PyTorch's
//! `FuseNetwork.load_state_dict(safetensors.torch.load_file(path))` takes our files and we take
//! files exported from it (float32 or float64; `num_batches_tracked` int64 and optional).
//! The header's metadata records the variant, the disparity range, the input normalisation and
//! how the file was made ([`WeightsInfo`]).

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use super::Error;
use super::network::{Architecture, Network};

/// The metadata of a weights file (safetensors `__metadata__`, all strings).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct WeightsInfo {
    /// Every key and value.
    pub entries: BTreeMap<String, String>,
}

impl WeightsInfo {
    /// A value.
    pub fn get(&self, key: &str) -> Option<&str> {
        self.entries.get(key).map(String::as_str)
    }

    /// Sets a value.
    pub fn set(&mut self, key: &str, value: impl Into<String>) {
        self.entries.insert(key.to_owned(), value.into());
    }
}

/// Whether the file's metadata asks for the refined estimate (`estimate = "refine"`: the
/// integer from the network, the sub-pixel offset from the inputs; see
/// `infer::Estimate::refine`) rather than the paper's soft-argmin (`"soft-argmin"`, or no entry,
/// as in files exported from PyTorch). Any other value is an error naming the file.
pub fn refine_recommended(info: &WeightsInfo, file: &str) -> Result<bool, Error> {
    match info.get("estimate") {
        None | Some("soft-argmin") => Ok(false),
        Some("refine") => Ok(true),
        Some(other) => Err(Error::Estimate {
            file: file.to_owned(),
            value: other.to_owned(),
        }),
    }
}

/// Context slices below the searched range the file's metadata asks inference to give the
/// network (`context_below`, see `crate::methods::mfusenet::MFuseNetConfig::room_below`); no
/// entry (files exported from PyTorch, networks trained without `--disparity-shift`) = 0. A value
/// that is not a multiple of 4 up to [`MAX_CONTEXT_BELOW`] is an error naming the file.
pub fn context_below_recommended(info: &WeightsInfo, file: &str) -> Result<usize, Error> {
    let Some(value) = info.get("context_below") else {
        return Ok(0);
    };
    value
        .parse::<usize>()
        .ok()
        .filter(|n| n.is_multiple_of(4) && *n <= MAX_CONTEXT_BELOW)
        .ok_or_else(|| Error::Metadata {
            file: file.to_owned(),
            key: "context_below",
            value: value.to_owned(),
            expected: "a multiple of 4 from 0 to 16",
        })
}

/// The correction of the refined readout's pixel locking the file carries (metadata
/// `locking_curve`, the JSON array of a [`crate::wta::LockingCurve`], fitted by `replay train`
/// on its training captures); no entry = none. A value that is not ten finite numbers in
/// [−1, 1] is an error naming the file.
pub fn locking_recommended(info: &WeightsInfo, file: &str) -> Result<Option<crate::wta::LockingCurve>, Error> {
    let Some(value) = info.get("locking_curve") else {
        return Ok(None);
    };
    serde_json::from_str::<crate::wta::LockingCurve>(value)
        .ok()
        .filter(|curve| curve.0.iter().all(|v| v.is_finite() && v.abs() <= 1.0))
        .map(Some)
        .ok_or_else(|| Error::Metadata {
            file: file.to_owned(),
            key: "locking_curve",
            value: value.to_owned(),
            expected: "a JSON array of ten numbers in [-1, 1]",
        })
}

/// How the file's inputs were made (metadata `input_spec`, the JSON of
/// [`super::input::InputSpec`], as `replay train` writes it); no entry (files exported from
/// PyTorch) = our default inputs. A value that does not parse is an error naming the file.
pub fn input_spec_recommended(info: &WeightsInfo, file: &str) -> Result<super::input::InputSpec, Error> {
    let Some(value) = info.get("input_spec") else {
        return Ok(super::input::InputSpec::default());
    };
    serde_json::from_str(value).map_err(|_| Error::Metadata {
        file: file.to_owned(),
        key: "input_spec",
        value: value.to_owned(),
        expected: "an input spec: {\"cost\": …, \"block_radius_px\": …, \"p1\": …, \"p2\": …}",
    })
}

/// How a sharp network's sharp volumes are made (metadata `sharp_spec`, the JSON of
/// [`super::input::SharpSpec`], as `replay train` writes it); no entry = the default. A value
/// that does not parse is an error naming the file.
pub fn sharp_spec_recommended(info: &WeightsInfo, file: &str) -> Result<super::input::SharpSpec, Error> {
    let Some(value) = info.get("sharp_spec") else {
        return Ok(super::input::SharpSpec::default());
    };
    serde_json::from_str(value).map_err(|_| Error::Metadata {
        file: file.to_owned(),
        key: "sharp_spec",
        value: value.to_owned(),
        expected: "a sharp spec: {\"cost\": …, \"unit\": …}",
    })
}

/// Metadata key and value that mark a view-count-agnostic network (`Network::views` = 0): its
/// `concat.0.weight` reads the pooled mean and maximum, 8 channels, the shape of the three-view
/// network's, so the shape alone cannot tell them apart.
pub const VIEW_FUSION_KEY: &str = "view_fusion";
/// See [`VIEW_FUSION_KEY`].
pub const MEAN_MAX: &str = "mean-max";

/// Metadata key of the layers' kernel sizes ([`Architecture::name`]: `paper` or `lite`). Files
/// without it (PyTorch's exports) are read by the kernel size of `concat.0.weight`: 7 the
/// paper's, 3 the lite one.
pub const ARCHITECTURE_KEY: &str = "architecture";

/// Most context slices below the range a weights file may ask for.
pub const MAX_CONTEXT_BELOW: usize = 16;

/// Every tensor of the reference `state_dict` for `views` inputs, with its shape, in the
/// reference's order.
pub fn state_dict_shapes(views: usize) -> Vec<(String, Vec<usize>)> {
    state_dict_shapes_with(views, Architecture::Paper)
}

/// [`state_dict_shapes`] of an architecture.
pub fn state_dict_shapes_with(views: usize, architecture: Architecture) -> Vec<(String, Vec<usize>)> {
    state_dict_shapes_of(&Network::zeros_with(views, architecture))
}

/// Every tensor of `net`'s `state_dict`, with its shape, in the reference's order.
fn state_dict_shapes_of(net: &Network) -> Vec<(String, Vec<usize>)> {
    let mut out = Vec::new();
    for layer in net.layers() {
        let c = layer.cout;
        out.push((format!("{}.0.weight", layer.name), layer.weight_shape().to_vec()));
        for field in ["weight", "bias", "running_mean", "running_var"] {
            out.push((format!("{}.1.{field}", layer.name), vec![c]));
        }
        out.push((format!("{}.1.num_batches_tracked", layer.name), vec![]));
    }
    out.push(("classify.weight".to_owned(), vec![1, 4, 3, 3, 3]));
    out.push(("classify.bias".to_owned(), vec![1]));
    out
}

/// Reads a weights file. `views`, when given, is the variant the caller needs (0: the
/// view-count-agnostic one): a file for another number of views is an error naming both.
pub fn load(path: &Path, views: Option<usize>) -> Result<(Network, WeightsInfo), Error> {
    let file = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| Error::Read {
        file: file.clone(),
        reason: e.to_string(),
    })?;
    from_bytes(&bytes, &file, "", views)
}

/// Reads weights from safetensors bytes; only tensors whose names start with `prefix` are the
/// model's (the prefix is stripped), so that test fixtures can hold more. `file` names the
/// source in errors.
pub fn from_bytes(
    bytes: &[u8],
    file: &str,
    prefix: &str,
    views: Option<usize>,
) -> Result<(Network, WeightsInfo), Error> {
    let format = |reason: String| Error::Format {
        file: file.to_owned(),
        reason,
    };
    let tensors = SafeTensors::deserialize(bytes).map_err(|e| format(e.to_string()))?;
    let (_, metadata) = SafeTensors::read_metadata(bytes).map_err(|e| format(e.to_string()))?;
    let info = WeightsInfo {
        entries: metadata.metadata().clone().unwrap_or_default().into_iter().collect(),
    };
    // Files exported from PyTorch carry no metadata; ours record the input normalisation.
    if let Some(steps) = info.get("input_steps_per_unit")
        && steps.parse::<f32>().ok() != Some(super::input::STEPS_PER_UNIT)
    {
        return Err(Error::Normalisation {
            file: file.to_owned(),
            expected: super::input::STEPS_PER_UNIT,
            got: steps.to_owned(),
        });
    }
    refine_recommended(&info, file)?;
    context_below_recommended(&info, file)?;
    input_spec_recommended(&info, file)?;
    sharp_spec_recommended(&info, file)?;
    locking_recommended(&info, file)?;
    let concat_name = format!("{prefix}concat.0.weight");
    let concat = tensors.tensor(&concat_name).map_err(|_| Error::MissingTensor {
        file: file.to_owned(),
        tensor: "concat.0.weight".to_owned(),
    })?;
    let pooled = match info.get(VIEW_FUSION_KEY) {
        None => false,
        Some(MEAN_MAX) => true,
        Some(other) => {
            return Err(Error::Metadata {
                file: file.to_owned(),
                key: VIEW_FUSION_KEY,
                value: other.to_owned(),
                expected: "\"mean-max\" (or no entry: the views side by side)",
            });
        }
    };
    let architecture = match info.get(ARCHITECTURE_KEY) {
        Some(name) => Architecture::from_name(name).ok_or_else(|| Error::Metadata {
            file: file.to_owned(),
            key: ARCHITECTURE_KEY,
            value: name.to_owned(),
            expected: "\"paper\" or \"lite\" (or no entry: read from the kernel size of concat.0.weight)",
        })?,
        None if concat.shape().get(2) == Some(&Architecture::Lite.concat_kernel()) => Architecture::Lite,
        None => Architecture::Paper,
    };
    let concat_k = architecture.concat_kernel();
    let channels = concat.shape().get(1).copied().unwrap_or(0);
    if pooled && channels != 8 {
        return Err(Error::TensorShape {
            file: file.to_owned(),
            tensor: "concat.0.weight".to_owned(),
            expected: format!("[4, 8, {concat_k}, {concat_k}, {concat_k}] (the pooled mean and maximum)"),
            got: concat.shape().to_vec(),
        });
    }
    // Four channels a view, or five with its sharp volume (`Network::sharp`): the two never
    // share a count for N = 1, 2, 4.
    let (found_views, sharp) = match channels {
        _ if pooled => (0, false),
        4 | 8 | 16 => (channels / 4, false),
        5 | 10 | 20 => (channels / 5, true),
        _ => {
            return Err(Error::TensorShape {
                file: file.to_owned(),
                tensor: "concat.0.weight".to_owned(),
                expected: format!(
                    "[4, 4·N or 5·N (with sharp volumes), {concat_k}, {concat_k}, {concat_k}] with N = 1, 2 or 4"
                ),
                got: concat.shape().to_vec(),
            });
        }
    };
    if let Some(expected) = views
        && expected != found_views
    {
        return Err(Error::Variant {
            file: file.to_owned(),
            expected,
            got: found_views,
        });
    }
    let mut values: HashMap<String, Vec<f32>> = HashMap::new();
    let mut batches: HashMap<String, i64> = HashMap::new();
    let template = Network::zeros_with(found_views, architecture);
    let template = if sharp {
        template.sharpened().unwrap_or(template)
    } else {
        template
    };
    let expected = state_dict_shapes_of(&template);
    for (name, shape) in &expected {
        let full = format!("{prefix}{name}");
        let tracked = name.ends_with("num_batches_tracked");
        let view = match tensors.tensor(&full) {
            Ok(view) => view,
            // PyTorch omits it with track_running_stats=False; it only counts passes.
            Err(_) if tracked => continue,
            Err(_) => {
                return Err(Error::MissingTensor {
                    file: file.to_owned(),
                    tensor: name.clone(),
                });
            }
        };
        if view.shape() != shape.as_slice() {
            return Err(Error::TensorShape {
                file: file.to_owned(),
                tensor: name.clone(),
                expected: format!("{shape:?}"),
                got: view.shape().to_vec(),
            });
        }
        if tracked {
            let count = match (view.dtype(), view.data()) {
                (Dtype::I64, data) if data.len() == 8 => i64::from_le_bytes(data.try_into().unwrap_or([0; 8])),
                (dtype, _) => {
                    return Err(Error::TensorDtype {
                        file: file.to_owned(),
                        tensor: name.clone(),
                        dtype: format!("{dtype:?}"),
                    });
                }
            };
            batches.insert(name.clone(), count);
            continue;
        }
        let floats = to_f32(&view).ok_or_else(|| Error::TensorDtype {
            file: file.to_owned(),
            tensor: name.clone(),
            dtype: format!("{:?}", view.dtype()),
        })?;
        if let Some(index) = floats.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                file: file.to_owned(),
                tensor: name.clone(),
                index,
            });
        }
        if name.ends_with("running_var")
            && let Some(index) = floats.iter().position(|v| *v < 0.0)
        {
            return Err(Error::NonFinite {
                file: file.to_owned(),
                tensor: name.clone(),
                index,
            });
        }
        values.insert(name.clone(), floats);
    }
    let unexpected: Vec<String> = tensors
        .names()
        .into_iter()
        .filter_map(|n| n.strip_prefix(prefix))
        .filter(|n| !expected.iter().any(|(e, _)| e == n))
        .map(str::to_owned)
        .collect();
    if let Some(tensor) = unexpected.into_iter().min() {
        return Err(Error::UnexpectedTensor {
            file: file.to_owned(),
            tensor,
        });
    }
    let mut net = template;
    let mut take = |name: String| values.remove(&name).unwrap_or_default();
    for layer in net.feature.iter_mut().chain(net.fuse.iter_mut()) {
        let n = layer.name.clone();
        layer.weight = take(format!("{n}.0.weight"));
        layer.bn.weight = take(format!("{n}.1.weight"));
        layer.bn.bias = take(format!("{n}.1.bias"));
        layer.bn.running_mean = take(format!("{n}.1.running_mean"));
        layer.bn.running_var = take(format!("{n}.1.running_var"));
        layer.bn.num_batches_tracked = batches.get(&format!("{n}.1.num_batches_tracked")).copied().unwrap_or(0);
        layer.bn.momentum = Some(crate::nn::batch_norm::MOMENTUM);
    }
    net.classify.weight = take("classify.weight".to_owned());
    net.classify.bias = take("classify.bias".to_owned());
    Ok((net, info))
}

fn to_f32(view: &TensorView<'_>) -> Option<Vec<f32>> {
    match view.dtype() {
        Dtype::F32 => Some(
            view.data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
        ),
        Dtype::F64 => Some(
            view.data()
                .chunks_exact(8)
                .map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32)
                .collect(),
        ),
        _ => None,
    }
}

/// The network as safetensors bytes (float32, `num_batches_tracked` int64), with `info` as the
/// header metadata.
pub fn to_bytes(net: &Network, info: &WeightsInfo) -> Result<Vec<u8>, Error> {
    let mut owned: Vec<(String, Dtype, Vec<usize>, Vec<u8>)> = Vec::new();
    let floats = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    for layer in net.layers() {
        let n = &layer.name;
        let c = vec![layer.cout];
        owned.push((
            format!("{n}.0.weight"),
            Dtype::F32,
            layer.weight_shape().to_vec(),
            floats(&layer.weight),
        ));
        owned.push((format!("{n}.1.weight"), Dtype::F32, c.clone(), floats(&layer.bn.weight)));
        owned.push((format!("{n}.1.bias"), Dtype::F32, c.clone(), floats(&layer.bn.bias)));
        owned.push((
            format!("{n}.1.running_mean"),
            Dtype::F32,
            c.clone(),
            floats(&layer.bn.running_mean),
        ));
        owned.push((
            format!("{n}.1.running_var"),
            Dtype::F32,
            c,
            floats(&layer.bn.running_var),
        ));
        owned.push((
            format!("{n}.1.num_batches_tracked"),
            Dtype::I64,
            vec![],
            layer.bn.num_batches_tracked.to_le_bytes().to_vec(),
        ));
    }
    owned.push((
        "classify.weight".to_owned(),
        Dtype::F32,
        vec![1, 4, 3, 3, 3],
        floats(&net.classify.weight),
    ));
    owned.push((
        "classify.bias".to_owned(),
        Dtype::F32,
        vec![1],
        floats(&net.classify.bias),
    ));
    let mut views = Vec::new();
    for (name, dtype, shape, data) in &owned {
        let view = TensorView::new(*dtype, shape.clone(), data).map_err(|e| Error::Format {
            file: name.clone(),
            reason: e.to_string(),
        })?;
        views.push((name.clone(), view));
    }
    let mut metadata: HashMap<String, String> = info.entries.clone().into_iter().collect();
    if net.views == 0 {
        metadata.insert(VIEW_FUSION_KEY.to_owned(), MEAN_MAX.to_owned());
    } else {
        metadata.remove(VIEW_FUSION_KEY);
    }
    match net.architecture {
        Architecture::Paper => metadata.remove(ARCHITECTURE_KEY),
        other => metadata.insert(ARCHITECTURE_KEY.to_owned(), other.name().to_owned()),
    };
    safetensors::serialize(views, Some(metadata)).map_err(|e| Error::Format {
        file: "(serialising)".to_owned(),
        reason: e.to_string(),
    })
}

/// Writes the network to `path` (through a temporary file renamed when complete).
pub fn save(net: &Network, info: &WeightsInfo, path: &Path) -> Result<(), Error> {
    let bytes = to_bytes(net, info)?;
    let file = path.display().to_string();
    let io = |e: std::io::Error| Error::Write {
        file: file.clone(),
        reason: e.to_string(),
    };
    let temporary = path.with_extension("safetensors.partial");
    std::fs::write(&temporary, bytes).map_err(io)?;
    std::fs::rename(&temporary, path).map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mfusenet::input::InputSpec;

    fn saved(net: &Network) -> Vec<u8> {
        to_bytes(net, &WeightsInfo::default()).unwrap_or_else(|e| panic!("{e}"))
    }

    /// Rebuilds a file from its tensors with one of them changed (`None` drops it).
    fn edited(bytes: &[u8], name: &str, change: Option<(Dtype, Vec<usize>, Vec<u8>)>) -> Vec<u8> {
        let tensors = SafeTensors::deserialize(bytes).unwrap_or_else(|e| panic!("{e}"));
        let mut owned: Vec<(String, Dtype, Vec<usize>, Vec<u8>)> = tensors
            .tensors()
            .into_iter()
            .map(|(n, v)| (n, v.dtype(), v.shape().to_vec(), v.data().to_vec()))
            .collect();
        owned.retain(|(n, ..)| n != name);
        if let Some((dtype, shape, data)) = change {
            owned.push((name.to_owned(), dtype, shape, data));
        }
        let views: Vec<(String, TensorView<'_>)> = owned
            .iter()
            .map(|(n, d, s, b)| {
                (
                    n.clone(),
                    TensorView::new(*d, s.clone(), b).unwrap_or_else(|e| panic!("{e}")),
                )
            })
            .collect();
        safetensors::serialize(views, None).unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn a_sharp_network_is_read_back_by_its_concat_shape() {
        for (views, architecture) in [
            (1, Architecture::Paper),
            (2, Architecture::Lite),
            (4, Architecture::Lite),
        ] {
            let mut net = Network::init_with(views, architecture, 3)
                .sharpened()
                .unwrap_or_else(|| panic!("a fixed network sharpens"));
            // Non-zero sharp weights, so that their places are checked.
            for (i, w) in net.fuse[0].weight.iter_mut().enumerate() {
                *w += 1e-3 * (i % 11) as f32;
            }
            let bytes = saved(&net);
            let (again, _) = from_bytes(&bytes, "w", "", Some(views)).unwrap_or_else(|e| panic!("{e}"));
            assert!(again.sharp, "N = {views}");
            assert_eq!(again, net, "N = {views}");
        }
        // Five channels a view, one view too many: an error naming the shapes it takes.
        let fixed = saved(&Network::init_with(2, Architecture::Lite, 3));
        let wrong = edited(
            &fixed,
            "concat.0.weight",
            Some((Dtype::F32, vec![4, 15, 3, 3, 3], vec![0u8; 4 * 15 * 27 * 4])),
        );
        let error = from_bytes(&wrong, "w", "", None).err();
        assert!(
            matches!(&error, Some(Error::TensorShape { tensor, expected, .. }) if tensor == "concat.0.weight" && expected.contains("5·N")),
            "{error:?}"
        );
    }

    #[test]
    fn a_lite_network_is_read_by_its_metadata_or_its_kernel_sizes() {
        let net = Network::init_with(4, Architecture::Lite, 9);
        let good = saved(&net);
        let (_, metadata) = SafeTensors::read_metadata(&good).unwrap_or_else(|e| panic!("{e}"));
        let entries = metadata.metadata().clone().unwrap_or_default();
        assert_eq!(entries.get(ARCHITECTURE_KEY).map(String::as_str), Some("lite"));
        let (again, _) = from_bytes(&good, "w", "", Some(4)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(again, net);
        // Without metadata (a PyTorch export): from `concat.0.weight`'s kernel size.
        let bare = edited(&good, "(none)", None);
        let (again, info) = from_bytes(&bare, "w", "", Some(4)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((again, info.get(ARCHITECTURE_KEY)), (net.clone(), None));
        // The paper's network writes no entry and reads back as the paper's.
        let paper = saved(&Network::init(4, 9));
        let (again, info) = from_bytes(&paper, "w", "", Some(4)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            (again.architecture, info.get(ARCHITECTURE_KEY)),
            (Architecture::Paper, None)
        );
        // Metadata that contradicts the shapes, or names no architecture: errors naming them.
        let relabelled = |name: &str| {
            let tensors = SafeTensors::deserialize(&good).unwrap_or_else(|e| panic!("{e}"));
            let views: Vec<(String, TensorView<'_>)> = tensors.tensors();
            let metadata = HashMap::from([(ARCHITECTURE_KEY.to_owned(), name.to_owned())]);
            safetensors::serialize(views, Some(metadata)).unwrap_or_else(|e| panic!("{e}"))
        };
        let error = from_bytes(&relabelled("paper"), "w", "", None).err();
        assert!(
            matches!(&error, Some(Error::TensorShape { tensor, .. }) if tensor == "feature.0.0.weight"),
            "{error:?}"
        );
        let error = from_bytes(&relabelled("tiny"), "w", "", None).err();
        assert!(
            matches!(&error, Some(Error::Metadata { key, value, .. }) if *key == ARCHITECTURE_KEY && value == "tiny"),
            "{error:?}"
        );
    }

    #[test]
    fn bad_weight_files_are_errors_naming_file_and_tensor() {
        let net = Network::init(2, 5);
        let good = saved(&net);
        let (again, _) = from_bytes(&good, "w.safetensors", "", Some(2)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(again, net);

        // Truncated.
        let error = from_bytes(&good[..good.len() / 2], "w.safetensors", "", None).err();
        assert!(
            matches!(&error, Some(Error::Format { file, .. }) if file == "w.safetensors"),
            "{error:?}"
        );
        assert!(from_bytes(b"not a file", "x", "", None).is_err());
        // Wrong variant.
        let error = from_bytes(&good, "w.safetensors", "", Some(4)).err();
        assert_eq!(
            error,
            Some(Error::Variant {
                file: "w.safetensors".into(),
                expected: 4,
                got: 2
            })
        );
        // Missing tensor.
        let error = from_bytes(&edited(&good, "down1.1.running_var", None), "w", "", None).err();
        assert!(
            matches!(&error, Some(Error::MissingTensor { tensor, .. }) if tensor == "down1.1.running_var"),
            "{error:?}"
        );
        // Wrong shape.
        let wrong = Some((Dtype::F32, vec![4, 4, 3, 3], vec![0u8; 4 * 4 * 9 * 4]));
        let error = from_bytes(&edited(&good, "dconv1.0.weight", wrong), "w", "", None).err();
        assert!(
            matches!(&error, Some(Error::TensorShape { tensor, .. }) if tensor == "dconv1.0.weight"),
            "{error:?}"
        );
        // NaN.
        let mut nan = vec![0u8; 16];
        nan[4..8].copy_from_slice(&f32::NAN.to_le_bytes());
        let error = from_bytes(
            &edited(&good, "up2.1.bias", Some((Dtype::F32, vec![4], nan))),
            "w",
            "",
            None,
        )
        .err();
        assert_eq!(
            error,
            Some(Error::NonFinite {
                file: "w".into(),
                tensor: "up2.1.bias".into(),
                index: 1
            })
        );
        // Wrong type.
        let error = from_bytes(
            &edited(&good, "up2.1.bias", Some((Dtype::I32, vec![4], vec![0; 16]))),
            "w",
            "",
            None,
        )
        .err();
        assert!(
            matches!(&error, Some(Error::TensorDtype { tensor, .. }) if tensor == "up2.1.bias"),
            "{error:?}"
        );
        // A tensor that is not the model's.
        let error = from_bytes(
            &edited(&good, "extra", Some((Dtype::F32, vec![1], vec![0; 4]))),
            "w",
            "",
            None,
        )
        .err();
        assert!(
            matches!(&error, Some(Error::UnexpectedTensor { tensor, .. }) if tensor == "extra"),
            "{error:?}"
        );
        // Trained on inputs normalised otherwise (the metadata says so).
        let mut info = WeightsInfo::default();
        info.set("input_steps_per_unit", "32");
        let other = to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}"));
        let error = from_bytes(&other, "w", "", None).err();
        assert!(
            matches!(&error, Some(Error::Normalisation { got, .. }) if got == "32"),
            "{error:?}"
        );
        info.set("input_steps_per_unit", super::super::input::STEPS_PER_UNIT.to_string());
        let ours = to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}"));
        assert!(from_bytes(&ours, "w", "", None).is_ok());
        // The estimate the file asks for: the paper's unless it says `refine`; nonsense is an error.
        let (_, read) = from_bytes(&ours, "w", "", None).unwrap_or_else(|e| panic!("{e}"));
        assert!(!refine_recommended(&read, "w").unwrap_or(true));
        info.set("estimate", "refine");
        let refining = to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}"));
        let (_, read) = from_bytes(&refining, "w", "", None).unwrap_or_else(|e| panic!("{e}"));
        assert!(refine_recommended(&read, "w").unwrap_or(false));
        info.set("estimate", "median");
        let error = from_bytes(&to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}")), "w", "", None).err();
        assert!(
            matches!(&error, Some(Error::Estimate { value, .. }) if value == "median"),
            "{error:?}"
        );
        // Context below the range: none unless the file says; a multiple of 4 up to 16.
        assert_eq!(context_below_recommended(&read, "w").ok(), Some(0));
        info.set("estimate", "refine");
        for (value, expected) in [
            ("4", Some(4)),
            ("16", Some(16)),
            ("3", None),
            ("20", None),
            ("four", None),
        ] {
            info.set("context_below", value);
            let result = from_bytes(&to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}")), "w", "", None);
            match expected {
                Some(n) => {
                    let (_, read) = result.unwrap_or_else(|e| panic!("{e}"));
                    assert_eq!(context_below_recommended(&read, "w").ok(), Some(n));
                }
                None => assert!(
                    matches!(&result, Err(Error::Metadata { key: "context_below", value: v, file, .. }) if v == value && file == "w"),
                    "{value}: {:?}",
                    result.err()
                ),
            }
        }
        // Inputs: ours unless the file says; what it says is read back; nonsense is an error.
        info.set("context_below", "0");
        let (_, read) = from_bytes(&to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}")), "w", "", None)
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(input_spec_recommended(&read, "w").ok(), Some(InputSpec::default()));
        let sharper = InputSpec {
            block_radius_px: 2,
            ..InputSpec::default()
        };
        info.set("input_spec", serde_json::to_string(&sharper).unwrap_or_default());
        let (_, read) = from_bytes(&to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}")), "w", "", None)
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(input_spec_recommended(&read, "w").ok(), Some(sharper));
        info.set("input_spec", "{\"block_radius_px\": \"wide\"}");
        let result = from_bytes(&to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}")), "w", "", None);
        assert!(
            matches!(&result, Err(Error::Metadata { key: "input_spec", file, .. }) if file == "w"),
            "{:?}",
            result.err()
        );
        // The locking curve: none unless the file says; ten numbers in [-1, 1], else an error.
        info.set(
            "input_spec",
            serde_json::to_string(&InputSpec::default()).unwrap_or_default(),
        );
        let (_, read) = from_bytes(&to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}")), "w", "", None)
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(locking_recommended(&read, "w").ok(), Some(None));
        let curve = crate::wta::LockingCurve([0.07, 0.13, 0.17, 0.2, 0.25, 0.27, 0.29, 0.33, 0.37, 0.31]);
        info.set("locking_curve", serde_json::to_string(&curve).unwrap_or_default());
        let (_, read) = from_bytes(&to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}")), "w", "", None)
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(locking_recommended(&read, "w").ok(), Some(Some(curve)));
        for bad in ["[0.1, 0.2]", "[0,0,0,0,0,0,0,0,0,3]", "steep"] {
            info.set("locking_curve", bad);
            let result = from_bytes(&to_bytes(&net, &info).unwrap_or_else(|e| panic!("{e}")), "w", "", None);
            assert!(
                matches!(&result, Err(Error::Metadata { key: "locking_curve", value, .. }) if value == bad),
                "{bad}: {:?}",
                result.err()
            );
        }
        // A missing file names it.
        let error = load(Path::new("/nonexistent/w.safetensors"), None).err();
        assert!(
            matches!(&error, Some(Error::Read { file, .. }) if file == "/nonexistent/w.safetensors"),
            "{error:?}"
        );
        // The messages carry the evidence.
        let message = Error::NonFinite {
            file: "w".into(),
            tensor: "up2.1.bias".into(),
            index: 1,
        }
        .to_string();
        assert!(message.contains("w") && message.contains("up2.1.bias"), "{message}");
    }

    #[test]
    fn shipped_weights_load_with_their_metadata() {
        // The stereo and three-view networks were trained with shifted crops (context below
        // their range); the five-view one was not, and its metadata asks for context since
        // (without it the network cannot answer in the range's first slices).
        // The lite five-view file too, whose range-start test needs 8 slices.
        for (views, file, expected_context, architecture) in [
            (1, "mfusenet-stereo", 4, Architecture::Paper),
            (2, "mfusenet-3view", 4, Architecture::Paper),
            (4, "mfusenet-5view", 4, Architecture::Paper),
            (4, "mfusenet-5view-lite", 8, Architecture::Lite),
        ] {
            let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("weights/{file}.safetensors"));
            let (net, info) = load(&path, Some(views)).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!((net.views, net.architecture), (views, architecture), "{file}");
            assert_eq!(info.get("views"), Some(views.to_string().as_str()), "{file}");
            assert!(
                info.get("made_by").is_some() && info.get("input_normalisation").is_some(),
                "{file}"
            );
            let context = context_below_recommended(&info, file).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(context, expected_context, "{file}");
        }
    }
}
