//! `--method`: building any of the ground segmentation methods from one configuration.

use anyhow::Result;
use clap::ValueEnum;
use groundwork_core::{GroundMethod, Segmenter};
use groundwork_io::MethodsConfig;
use groundwork_pseudolabel::{GroundFrame, PseudoLabeler, Ransac};

/// A ground segmentation method.
#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum MethodArg {
    /// The GMM segmenter (online; multi-frame history with poses).
    Gmm,
    /// TerraSeg's PseudoLabeler (offline, per-scan MLP elevation map).
    Pseudolabeler,
    /// The RANSAC plane baseline.
    Ransac,
}

impl MethodArg {
    /// The name on the command line (`gmm`, `pseudolabeler`, `ransac`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Gmm => "gmm",
            Self::Pseudolabeler => "pseudolabeler",
            Self::Ransac => "ransac",
        }
    }
}

/// The method, configured: the sensor section (mount, ego radius, maximum points) serves
/// all three.
pub fn build(method: MethodArg, cfg: &MethodsConfig) -> Result<Box<dyn GroundMethod>> {
    let frame = || GroundFrame::from_config(&cfg.segmenter);
    Ok(match method {
        MethodArg::Gmm => Box::new(Segmenter::new(cfg.segmenter.clone())?),
        MethodArg::Pseudolabeler => {
            Box::new(PseudoLabeler::new(cfg.pseudolabeler.clone(), frame()?)?)
        }
        MethodArg::Ransac => Box::new(Ransac::new(cfg.ransac.clone(), frame()?)?),
    })
}
