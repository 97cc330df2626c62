//! MFuseNet (paper, section IV): each neighbour's cost volume aggregated on its own by SGM, the
//! volumes fused by the trained 3D CNN, disparity by soft-argmin (`crate::mfusenet`).
//!
//! `mfusenet` picks the network from the set's neighbours: five-view (left, right, top, bottom)
//! when all four are there, else three-view (left and right, or top and bottom), else the
//! stereo network; `mfusenet-stereo` always takes the stereo network and the `right` view.
//! The trained weights of the three variants are compiled into the binary (`fuse/weights/`,
//! made by `replay train`, see `fuse/weights/README.md`); `{"weights": "FILE"}` (or replay's
//! `--weights FILE`) takes a safetensors file instead, whose variant must fit the set.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{Family, Method, MethodEntry, Progress, apply_overrides};
use crate::FuseError;
use crate::image::DisparityImage;
use crate::mfusenet::infer::{DEFAULT_TILE_BUDGET_BYTES, Estimate, infer};
use crate::mfusenet::input::{InputSpec, input_volumes, ordered_neighbours, views_for};
use crate::mfusenet::{Network, weights};
use crate::postprocess::median3x3;
use crate::volume::Problem;

/// The shipped weights, per number of input volumes.
const SHIPPED: [(usize, &str, &[u8]); 3] = [
    (
        1,
        "mfusenet-stereo.safetensors",
        include_bytes!("../../weights/mfusenet-stereo.safetensors"),
    ),
    (
        2,
        "mfusenet-3view.safetensors",
        include_bytes!("../../weights/mfusenet-3view.safetensors"),
    ),
    (
        4,
        "mfusenet-5view.safetensors",
        include_bytes!("../../weights/mfusenet-5view.safetensors"),
    ),
];

/// Configuration of MFuseNet.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MFuseNetConfig {
    /// A safetensors weights file (the reference `state_dict`'s names); `null` = the shipped
    /// weights of the variant the set needs.
    pub weights: Option<String>,
    /// How each neighbour's input volume is made (must match the training).
    pub input: InputSpec,
    /// Memory budget of one tile's activations (MiB); larger images are cut into tiles.
    pub tile_budget_mib: usize,
    /// Soft-argmin only over this many disparities either side of the most probable one
    /// (`null` = over the whole range, as in the paper); see `mfusenet::infer::infer`.
    pub window: Option<usize>,
    /// Sub-pixel from the inputs: the integer nearest the network's estimate, refined by a
    /// parabola through the summed input costs (see `mfusenet::infer::Estimate`).
    pub refine: bool,
    /// A 3×3 median on the result (as block matching and SGM do).
    pub median: bool,
}

impl Default for MFuseNetConfig {
    fn default() -> Self {
        Self {
            weights: None,
            input: InputSpec::default(),
            tile_budget_mib: DEFAULT_TILE_BUDGET_BYTES >> 20,
            window: None,
            refine: false,
            median: false,
        }
    }
}

/// MFuseNet with its networks loaded.
pub struct MFuseNet {
    name: &'static str,
    config: MFuseNetConfig,
    /// `(views, network)`: the shipped three, or the one from `weights`.
    networks: Vec<(usize, Network)>,
    /// Only the stereo network and neighbour.
    stereo: bool,
}

impl MFuseNet {
    /// Loads the networks (`weights` or the shipped ones); bad files are errors naming the file
    /// and the tensor.
    pub fn new(name: &'static str, config: MFuseNetConfig, stereo: bool) -> Result<Self, FuseError> {
        let networks = match &config.weights {
            Some(path) => {
                let (net, _) = weights::load(Path::new(path), stereo.then_some(1))?;
                vec![(net.views, net)]
            }
            None => SHIPPED
                .iter()
                .filter(|(views, ..)| !stereo || *views == 1)
                .map(|(views, file, bytes)| {
                    let (net, _) = weights::from_bytes(bytes, &format!("(shipped) {file}"), "", Some(*views))?;
                    Ok((*views, net))
                })
                .collect::<Result<_, FuseError>>()?,
        };
        Ok(Self {
            name,
            config,
            networks,
            stereo,
        })
    }

    /// The network for a problem and how many volumes it takes.
    fn network_for(&self, problem: &Problem) -> Result<&Network, FuseError> {
        let views = match (&self.config.weights, self.stereo) {
            (_, true) => 1,
            (Some(_), false) => self.networks.first().map_or(1, |(v, _)| *v),
            (None, false) => views_for(problem),
        };
        self.networks
            .iter()
            .find(|(v, _)| *v == views)
            .map(|(_, net)| net)
            .ok_or(FuseError::Config {
                field: "weights",
                value: String::new(),
                reason: "no network for this number of neighbours",
            })
    }
}

impl Method for MFuseNet {
    fn name(&self) -> &str {
        self.name
    }

    fn config_json(&self) -> serde_json::Value {
        serde_json::to_value(&self.config).unwrap_or_default()
    }

    fn run(&self, problem: &Problem, progress: Progress<'_>) -> Result<DisparityImage, FuseError> {
        problem.validate()?;
        let net = self.network_for(problem)?;
        let neighbours = ordered_neighbours(problem, net.views)?;
        // Cost volumes: about a tenth of the work; the network the rest.
        let volumes = input_volumes(problem, &neighbours, self.config.input, &|| {})?;
        progress(0.1);
        let data = infer(
            net,
            &volumes,
            self.config.tile_budget_mib << 20,
            Estimate {
                window: self.config.window,
                refine: self.config.refine,
            },
            &|f| progress(0.1 + 0.9 * f),
        )?;
        let disparity = DisparityImage {
            width: problem.reference.width,
            height: problem.reference.height,
            data,
        };
        Ok(if self.config.median {
            median3x3(&disparity)
        } else {
            disparity
        })
    }
}

fn build(
    name: &'static str,
    stereo: bool,
    overrides: Option<&serde_json::Value>,
) -> Result<Box<dyn Method>, FuseError> {
    let config = apply_overrides(MFuseNetConfig::default(), overrides)?;
    Ok(Box::new(MFuseNet::new(name, config, stereo)?))
}

/// Registry entries.
pub const ENTRIES: &[MethodEntry] = &[
    MethodEntry {
        name: "mfusenet-stereo",
        summary: "MFuseNet on one cost volume (the right view's, SGM-aggregated census): the paper's learned stereo baseline",
        family: Family::MFuseNet,
        build: |o| build("mfusenet-stereo", true, o),
    },
    MethodEntry {
        name: "mfusenet",
        summary: "MFuseNet: the per-neighbour SGM cost volumes fused by the trained 3D CNN (five-, three- or two-view network from the set)",
        family: Family::MFuseNet,
        build: |o| build("mfusenet", false, o),
    },
];
