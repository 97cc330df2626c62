//! Small deterministic random numbers for scenes, stations and noise: the workspace's one
//! generator, [`fuse::rng`], re-exported.

pub use fuse::rng::*;
