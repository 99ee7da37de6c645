//! The Fig.-6-style comparison figure of one frame:
//! RGB | ground truth | raw prediction | SSRA | GSSA | LWLR on one shared colour scale in metres
//! (the raw prediction, unitless, on its own scale), and below an error row |aligned − GT| in
//! millimetres on its own shared scale.

use std::path::Path;

use moma_core::{MetricDepth, Prediction, is_valid_depth};
use ndarray::Array2;

use crate::data::LoadedFrame;
use crate::error::Result;
use crate::render::{FigureRow, Panel, comparison_figure, quantile, source_caption};

/// Panel width in pixels of the figures.
pub const FIGURE_PANEL_W: u32 = 300;

/// Writes the figure of one frame. `aligned` are `(method label, aligned depth)` in panel order.
/// The figure's title is `title` followed by the prediction source ([`source_caption`] of
/// `source_label` and `simulated`), so no figure leaves out where its predictions came from.
///
/// # Errors
/// Drawing or I/O failure.
pub fn frame_figure(
    path: &Path,
    title: &str,
    frame: &LoadedFrame,
    raw: &Prediction,
    source_label: &str,
    simulated: bool,
    aligned: &[(String, MetricDepth)],
) -> Result<()> {
    let gt = &frame.gt.depth_m;
    let valid_gt = || gt.iter().copied().filter(|&z| is_valid_depth(z));
    let mut lo = quantile(valid_gt(), 0.02);
    let mut hi = quantile(valid_gt(), 0.98);
    if hi.is_nan() || lo.is_nan() || hi <= lo {
        lo = 0.0;
        hi = 1.0;
    }
    let mut top: Vec<(String, Panel)> = Vec::new();
    let mut bottom: Vec<(String, Panel)> = Vec::new();
    match &frame.rgb {
        Some(rgb) => top.push(("RGB".into(), Panel::Rgb(rgb.clone()))),
        None => top.push(("RGB (none)".into(), Panel::Empty)),
    }
    match &frame.mask {
        Some(m) => bottom.push(("evaluation mask".into(), Panel::Mask(m.clone()))),
        None => bottom.push(("(no mask: whole image)".into(), Panel::Empty)),
    }
    top.push(("ground truth".into(), Panel::Metres(gt.clone())));
    bottom.push((String::new(), Panel::Empty));
    let raw_title = if simulated {
        format!("SIMULATED {} (own scale)", raw.kind)
    } else {
        format!("raw {} (own scale)", raw.kind)
    };
    top.push((raw_title, Panel::Unitless(raw.values.clone())));
    bottom.push((String::new(), Panel::Empty));
    let mut errs: Vec<f32> = Vec::new();
    let mut err_maps: Vec<Array2<f32>> = Vec::new();
    for (name, d) in aligned {
        top.push((name.to_uppercase(), Panel::Metres(d.depth_m.clone())));
        let e = ndarray::Zip::from(&d.depth_m)
            .and(gt)
            .map_collect(|&p, &g| {
                if is_valid_depth(g) && p.is_finite() {
                    (p - g).abs()
                } else {
                    f32::NAN
                }
            });
        match &frame.mask {
            Some(m) => errs.extend(
                e.iter()
                    .zip(m.data().iter())
                    .filter(|(_, inside)| **inside)
                    .map(|(x, _)| *x),
            ),
            None => errs.extend(e.iter().copied()),
        }
        err_maps.push(e);
    }
    let mut emax = quantile(errs.into_iter(), 0.98);
    if emax.is_nan() || emax <= 0.0 {
        emax = 0.01;
    }
    for ((name, _), e) in aligned.iter().zip(err_maps) {
        bottom.push((format!("|error| {}", name.to_uppercase()), Panel::Metres(e)));
    }
    let rows = [
        FigureRow {
            panels: top,
            bar_label: "depth [m]".into(),
            range: (lo, hi),
            tick_scale: 1.0,
        },
        FigureRow {
            panels: bottom,
            bar_label: "|error| [mm]".into(),
            range: (0.0, emax),
            tick_scale: 1000.0,
        },
    ];
    let title = format!("{title} — {}", source_caption(source_label, simulated));
    comparison_figure(path, &title, &rows, FIGURE_PANEL_W)
}
