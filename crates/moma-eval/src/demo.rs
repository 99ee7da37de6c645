//! `moma demo`: the whole idea in one call. Builds the procedural scene ([`crate::scene`]),
//! simulates predictions ([`crate::simulate`]), calibrates on the first frame, aligns the others,
//! and writes tables, figures, aligned depth (PNG16 mm + npy), colour maps and point clouds.

use std::path::{Path, PathBuf};

use moma_core::PredictionKind;
use moma_core::normalise::NormalisationConfig;

use moma_io::{Colormap, DepthRange, PlyFormat};

use crate::data::{LoadedSet, create_parent};
use crate::error::Result;
use crate::figure::frame_figure;
use crate::protocol::{EvalConfig, PredictionSet, Prepared, aligned_maps};
use crate::render::quantile;
use crate::scene::{DemoSceneConfig, build_scene};
use crate::simulate::{
    Simulator, SimulatorConfig, TransparencySource, simulate_frames, simulate_set,
};

/// What [`write_visuals`] wrote.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct VisualFiles {
    /// Figures, one per frame.
    pub figures: Vec<PathBuf>,
    /// Aligned depth PNG16 (mm) and npy (m) files.
    pub depth: Vec<PathBuf>,
    /// Colour maps.
    pub colour_maps: Vec<PathBuf>,
    /// Point clouds.
    pub point_clouds: Vec<PathBuf>,
}

/// Aligns every frame with every method of `config` for the first seed and writes, per frame,
/// the comparison figure (`figures/<frame>.png`), aligned depth (`aligned/<method>/<frame>.png`
/// uint16 mm and `.npy` float32 m), colour maps (`aligned/<method>/<frame>_colour.png`) and with
/// `point_clouds` a PLY per frame of the SSRA (or first) method (`pointclouds/<frame>_<method>.ply`).
///
/// # Errors
/// Any alignment or I/O failure, naming the frame.
pub fn write_visuals(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &EvalConfig,
    out: &Path,
    exports: bool,
) -> Result<VisualFiles> {
    let prep = Prepared::new(set, preds, config)?;
    let mut files = VisualFiles::default();
    let norm0 = prep.first_norm();
    let mut per_method: Vec<(String, Vec<moma_core::MetricDepth>)> = Vec::new();
    for m in &config.methods {
        let norm: NormalisationConfig = prep.normalisation_for(m, norm0);
        let (_, maps) = aligned_maps(&prep, m, &norm, config.samples, config.seed_base)?;
        per_method.push((m.to_string(), maps));
    }
    let pc_method = per_method
        .iter()
        .position(|(m, _)| m == "ssra")
        .unwrap_or(0);
    for (i, f) in set.frames.iter().enumerate() {
        let valid =
            f.gt.depth_m
                .iter()
                .copied()
                .filter(|&z| moma_core::is_valid_depth(z));
        let lo = quantile(valid.clone(), 0.02);
        let hi = quantile(valid, 0.98);
        // the ground truth's 2–98 % range for every map of the frame (automatic if degenerate)
        let (min_m, max_m) = (lo as f32, hi as f32);
        let range = if min_m.is_finite() && max_m.is_finite() && min_m < max_m {
            DepthRange::Fixed { min_m, max_m }
        } else {
            DepthRange::default()
        };
        let role = if i == prep.calib {
            "calibration frame"
        } else {
            "evaluated frame"
        };
        let figure_methods: Vec<(String, moma_core::MetricDepth)> = per_method
            .iter()
            .filter(|(m, _)| m != "raw")
            .map(|(m, maps)| (m.clone(), maps[i].clone()))
            .collect();
        // frame_figure appends the prediction source (SIMULATED / the model) to the title
        let title = format!(
            "{} / {} ({role}; calibrated on {}, n = {}, seed {})",
            set.name,
            f.id,
            prep.calib_id(),
            config.samples,
            config.seed_base,
        );
        let fig = out.join("figures").join(format!("{}.png", f.id));
        frame_figure(
            &fig,
            &title,
            f,
            &preds.maps[i],
            &preds.label,
            preds.simulated,
            &figure_methods,
        )?;
        files.figures.push(fig);
        if !exports {
            continue;
        }
        for (m, maps) in &per_method {
            let dir = out.join("aligned").join(m);
            let png = dir.join(format!("{}.png", f.id));
            create_parent(&png)?;
            // the folder's aligned.json says where these depths came from (`moma metrics`
            // labels a SIMULATED one so)
            let entry = |file: String| moma_io::AlignedFile {
                file,
                simulated: preds.simulated,
                written_by: "moma demo".into(),
                calibration: None,
                method: Some(m.clone()),
                input: Some(preds.label.clone()),
            };
            let entries = || {
                vec![
                    entry(format!("{}.png", f.id)),
                    entry(format!("{}.npy", f.id)),
                ]
            };
            moma_io::record_before_writing(&dir, entries())?;
            moma_io::write_depth(&png, &maps[i])?;
            let npy = dir.join(format!("{}.npy", f.id));
            moma_io::write_npy_f32(&npy, maps[i].depth_m.view())?;
            moma_io::record_aligned_files(&dir, entries())?;
            let col = dir.join(format!("{}_colour.png", f.id));
            moma_io::write_depth_colormap(&col, &maps[i], Colormap::Turbo, range)?;
            files.depth.push(png);
            files.depth.push(npy);
            files.colour_maps.push(col);
        }
        if let Some((m, maps)) = per_method.get(pc_method) {
            let ply = out.join("pointclouds").join(format!("{}_{m}.ply", f.id));
            create_parent(&ply)?;
            moma_io::write_depth_ply(
                &ply,
                &maps[i],
                &set.intrinsics,
                f.rgb.as_ref(),
                PlyFormat::BinaryLittleEndian,
            )?;
            files.point_clouds.push(ply);
        }
    }
    Ok(files)
}

/// Draws the top-5 suction grasps planned on one evaluated frame (the first after the
/// calibration frame) with the deployed configuration, SSRA (or the first method),
/// re-aligned when `config.realign` is set, ranked robust under the frame's error model, onto
/// its RGB (or the colour-mapped depth): `grasps/<frame>_suction.png` (best green, then yellow to
/// red). Returns the path.
///
/// # Errors
/// Alignment, planning or I/O failures, naming the frame.
pub fn write_grasp_overlay(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &EvalConfig,
    out: &Path,
) -> Result<PathBuf> {
    use moma_grasp::{GraspRequest, Gripper, SuctionCup, plan_grasps};
    let prep = Prepared::new(set, preds, config)?;
    let method = config
        .methods
        .iter()
        .find(|m| m.to_string() == "ssra")
        .or(config.methods.first())
        .ok_or_else(|| crate::EvalError::InvalidParameter("no method to plan with".into()))?;
    let method = prep.method(method);
    let norm = prep.normalisation_for(&method, prep.first_norm());
    let i = *prep.eval_indices().first().ok_or_else(|| {
        crate::EvalError::InvalidParameter("the set has no frame to plan on".into())
    })?;
    let seed = config.seed_base;
    let (depth, model) = match &config.realign {
        Some(r) => {
            let setup = crate::realign::RealignSetup::new(&prep, &norm, r, 1.0)?;
            let cal = setup.calibrate(&prep, &method, &norm, config.samples, seed)?;
            let (d, report) = setup.realign_frame(&prep, &cal, i, seed)?;
            (d, cal.frame_error_model(Some(&report)))
        }
        None => {
            let maps = prep.normalised_all(&norm)?;
            let cal = prep.calibrate(&method, &norm, &maps[prep.calib], config.samples, seed)?;
            let (d, _) = prep.score(&cal, &maps[i], i)?;
            (d, cal.frame_error_model(None))
        }
    };
    let f = &set.frames[i];
    let gripper = Gripper::Suction(SuctionCup::default());
    let mut request = GraspRequest::new(gripper).with_error_model(model);
    request.top_k = 5;
    request.seed = seed;
    let (_, outcome) = plan_grasps(&depth, &set.intrinsics, f.mask.as_ref(), &request)
        .map_err(|e| crate::EvalError::frame(&set.name, &f.id, format!("grasp planner: {e}")))?;
    let img = match &f.rgb {
        Some(rgb) => rgb.clone(),
        None => {
            moma_io::colourise_depth(&depth, Colormap::Turbo, DepthRange::default())
                .map_err(|e| {
                    crate::EvalError::core(format!("set '{}', frame '{}'", set.name, f.id), e)
                })?
                .0
        }
    };
    let path = out.join("grasps").join(format!("{}_suction.png", f.id));
    let variant = if config.realign.is_some() {
        "re-aligned on static anchors"
    } else {
        "one-shot"
    };
    let title = [
        format!(
            "suction, top {}: {}-aligned depth ({variant}) of {}",
            request.top_k,
            method.name().to_uppercase(),
            f.id
        ),
        crate::render::source_caption(&preds.label, preds.simulated),
        crate::render::success_prob_caption(Some("the calibration's error model")),
        "ranked robust: by success_prob, near ties by the planner's score".to_string(),
    ];
    create_parent(&path)?;
    crate::render::write_grasp_overlay(&path, img, &set.intrinsics, &outcome, &gripper, &title)?;
    Ok(path)
}

/// Settings of the bundled demo scene and its simulated predictions.
#[derive(Debug, Clone, PartialEq)]
pub struct DemoScene {
    /// Scene geometry.
    pub scene: DemoSceneConfig,
    /// Simulator strengths.
    pub simulator: SimulatorConfig,
    /// Simulator seed.
    pub simulator_seed: u64,
    /// Kind of the simulated predictions (inverse depth, like Depth Anything V2's relative models).
    pub kind: PredictionKind,
}

impl Default for DemoScene {
    fn default() -> Self {
        Self {
            scene: DemoSceneConfig::default(),
            simulator: SimulatorConfig::default(),
            simulator_seed: 0,
            kind: PredictionKind::RelativeDisparity,
        }
    }
}

/// Builds the demo scene and its simulated predictions; with `out`, writes the scene in the moma
/// layout to `out/scene/` and the predictions (with `predictions.json`) to `out/predictions/`.
///
/// # Errors
/// Simulation or I/O failure.
pub fn build_demo(demo: &DemoScene, out: Option<&Path>) -> Result<(LoadedSet, PredictionSet)> {
    let mut set = build_scene(&demo.scene);
    let sim = Simulator::new(
        demo.simulator,
        demo.simulator_seed,
        demo.kind,
        set.intrinsics,
    )?;
    let maps = match out {
        Some(dir) => {
            let scene_dir = dir.join("scene");
            crate::data::write_set(&scene_dir, &set)?;
            set.dir = scene_dir;
            simulate_set(
                &set,
                &sim,
                TransparencySource::None,
                &dir.join("predictions"),
            )?
            .1
        }
        None => simulate_frames(&set, &sim, TransparencySource::None)?,
    };
    Ok((
        set,
        PredictionSet {
            label: format!("SIMULATED {}", demo.kind),
            simulated: true,
            maps,
        },
    ))
}
