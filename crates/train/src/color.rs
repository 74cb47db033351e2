//! The trainer's side of the per-view colour correction (`TrainConfig::color_correction`,
//! `nerf_render::color_correct_forward`): the corrections on the CPU, and their name in
//! checkpoints (`color/…`, see [`crate::views`]).

use crate::views::{CpuViews, ViewKind, ViewState};
use nerf_optim::AdamConfig;
use nerf_render::{identity_color_correction, COLOR_PARAMS_PER_VIEW};

/// The colour corrections' entries in checkpoints (`color/params`, 12 values per training view,
/// `color/m`, `color/v`, `color/step`) and their Adam group.
pub const COLOR_VIEWS: ViewKind = ViewKind {
    prefix: "color/",
    group: "color_correction",
    per_view: COLOR_PARAMS_PER_VIEW,
    what: "colour correction",
};
/// Name of the corrections' Adam group.
pub const COLOR_GROUP: &str = COLOR_VIEWS.group;

/// The colour corrections and their optimiser state, as a checkpoint holds them.
pub type ColorState = ViewState;

/// The CPU path's corrections, with the per-step buffers.
pub(crate) struct CpuColor {
    pub views: CpuViews,
    pub lr: f32,
    /// Corrected pixels (`3·n_rays`), and what compositing's backward gets.
    pub out: Vec<f32>,
    pub d_rgb: Vec<f32>,
    pub d_opacity: Vec<f32>,
}

impl CpuColor {
    pub fn new(n_views: usize, adam: &AdamConfig, lr: f32) -> Self {
        let views = CpuViews::new(COLOR_VIEWS, identity_color_correction(n_views), adam);
        Self { views, lr, out: Vec::new(), d_rgb: Vec::new(), d_opacity: Vec::new() }
    }
}
