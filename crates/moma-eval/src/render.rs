//! Pictures: colour maps, the embedded font, line and bar plots (plotters, bitmap backend) and
//! the Fig.-6-style comparison figure. No system font is needed: DejaVu Sans is embedded.

use std::path::Path;
use std::sync::Once;

use image::RgbImage;
use moma_core::{Mask, is_valid_depth};
use moma_io::Colormap;
use plotters::prelude::*;
use plotters::style::FontStyle;

use crate::data::create_parent;
use crate::error::{EvalError, Result};

/// Font family name under which the embedded DejaVu Sans is registered.
pub const FONT: &str = "sans-serif";

/// Registers the embedded DejaVu Sans with plotters (idempotent).
pub fn register_fonts() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // Registration only fails for an invalid font file; the embedded one is valid.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
        let _ = plotters::style::register_font(FONT, FontStyle::Bold, dejavu::sans::bold());
    });
}

/// Colour of invalid pixels in depth pictures.
pub const INVALID_RGB: [u8; 3] = [40, 40, 40];

/// Colourises a map with [`Colormap::Turbo`] over `[lo, hi]` through moma-io's colouriser
/// ([`moma_io::colourise_with`], the one `moma align --colormap` uses); invalid pixels dark grey
/// ([`INVALID_RGB`]).
pub fn colourise(
    values: &ndarray::Array2<f32>,
    lo: f64,
    hi: f64,
    valid: impl Fn(f32) -> bool,
) -> RgbImage {
    moma_io::colourise_with(
        values.view(),
        Colormap::Turbo,
        lo as f32,
        hi as f32,
        valid,
        INVALID_RGB,
    )
}

/// What every plot and figure says about its predictions: `SIMULATED predictions (<label>)` for
/// simulator output, else `predictions: <label>` (the label names the model, and says
/// "random weights" for a network without trained weights).
pub fn source_caption(label: &str, simulated: bool) -> String {
    if simulated {
        format!("SIMULATED predictions ({label})")
    } else {
        format!("predictions: {label}")
    }
}

/// Height in pixels of the strip above a plot that names the prediction source.
const SOURCE_STRIP_H: u32 = 28;

/// Draws `source` (see [`source_caption`]) in the strip at the top of `root` and returns the area
/// below it.
fn source_strip<'a>(
    path: &Path,
    root: &DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>,
    source: &str,
) -> Result<DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>> {
    let (top, rest) = root.split_vertically(SOURCE_STRIP_H);
    top.draw(&Text::new(
        source.to_string(),
        (12, 6),
        (FONT, 16).into_font().color(&BLACK),
    ))
    .map_err(|e| plot_err(path, e))?;
    Ok(rest)
}

/// The `p`-quantile (0..1) of the finite values (NaN when none).
pub fn quantile(values: impl Iterator<Item = f32>, p: f64) -> f64 {
    let mut v: Vec<f32> = values.filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return f64::NAN;
    }
    let k = ((v.len() - 1) as f64 * p).round() as usize;
    let (_, x, _) = v.select_nth_unstable_by(k, f32::total_cmp);
    *x as f64
}

fn plot_err(path: &Path, e: impl std::fmt::Debug) -> EvalError {
    EvalError::Plot {
        path: path.to_path_buf(),
        message: format!("{e:?}"),
    }
}

fn series_colour(i: usize) -> RGBColor {
    const C: [RGBColor; 8] = [
        RGBColor(214, 39, 40),
        RGBColor(31, 119, 180),
        RGBColor(44, 160, 44),
        RGBColor(127, 127, 127),
        RGBColor(255, 127, 14),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(23, 190, 207),
    ];
    C[i % C.len()]
}

/// One named series of `(x, mean, std)` points.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend label.
    pub name: String,
    /// Points `(x, y mean, y std)`.
    pub points: Vec<(f64, f64, f64)>,
}

/// One panel of a line plot.
#[derive(Debug, Clone, PartialEq)]
pub struct LinePanel {
    /// Caption.
    pub title: String,
    /// x-axis label.
    pub x_label: String,
    /// y-axis label.
    pub y_label: String,
    /// Logarithmic x axis.
    pub log_x: bool,
    /// Logarithmic y axis.
    pub log_y: bool,
    /// The series.
    pub series: Vec<Series>,
}

fn range_of(series: &[Series], f: impl Fn(&(f64, f64, f64)) -> [f64; 2], log: bool) -> (f64, f64) {
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for s in series {
        for p in &s.points {
            for v in f(p) {
                if v.is_finite() && (!log || v > 0.0) {
                    lo = lo.min(v);
                    hi = hi.max(v);
                }
            }
        }
    }
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if log {
        (lo / 1.5, hi * 1.5)
    } else {
        let pad = ((hi - lo) * 0.08).max(1e-9);
        (
            (lo - pad).min(if lo >= 0.0 { 0.0 } else { lo - pad }),
            hi + pad,
        )
    }
}

/// Draws panels side by side into a PNG of `panel_w × panel_h` pixels per panel, under a strip
/// naming the prediction `source` (see [`source_caption`]).
///
/// # Errors
/// Drawing or I/O failure.
pub fn line_plot(
    path: &Path,
    source: &str,
    panels: &[LinePanel],
    panel_w: u32,
    panel_h: u32,
) -> Result<()> {
    register_fonts();
    let (w, h) = (
        panel_w * panels.len().max(1) as u32,
        panel_h + SOURCE_STRIP_H,
    );
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| plot_err(path, e))?;
        let root = source_strip(path, &root, source)?;
        let areas = root.split_evenly((1, panels.len().max(1)));
        for (panel, area) in panels.iter().zip(areas.iter()) {
            let (x0, x1) = range_of(&panel.series, |p| [p.0, p.0], panel.log_x);
            let (y0, y1) = range_of(&panel.series, |p| [p.1 - p.2, p.1 + p.2], panel.log_y);
            let mut cb = ChartBuilder::on(area);
            cb.caption(&panel.title, (FONT, 20))
                .margin(12)
                .x_label_area_size(45)
                .y_label_area_size(70);
            macro_rules! draw {
                ($chart:expr) => {{
                    let mut chart = $chart;
                    chart
                        .configure_mesh()
                        .x_desc(panel.x_label.as_str())
                        .y_desc(panel.y_label.as_str())
                        .label_style((FONT, 14))
                        .axis_desc_style((FONT, 15))
                        .draw()
                        .map_err(|e| plot_err(path, e))?;
                    for (i, s) in panel.series.iter().enumerate() {
                        let c = series_colour(i);
                        chart
                            .draw_series(LineSeries::new(
                                s.points.iter().map(|p| (p.0, p.1)),
                                c.stroke_width(2),
                            ))
                            .map_err(|e| plot_err(path, e))?
                            .label(s.name.as_str())
                            .legend(move |(x, y)| {
                                PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
                            });
                        chart
                            .draw_series(
                                s.points
                                    .iter()
                                    .map(|p| Circle::new((p.0, p.1), 3, c.filled())),
                            )
                            .map_err(|e| plot_err(path, e))?;
                        chart
                            .draw_series(s.points.iter().filter(|p| p.2 > 0.0).map(|p| {
                                let lo = if panel.log_y {
                                    (p.1 - p.2).max(p.1 * 0.5)
                                } else {
                                    p.1 - p.2
                                };
                                PathElement::new(
                                    vec![(p.0, lo), (p.0, p.1 + p.2)],
                                    c.stroke_width(1),
                                )
                            }))
                            .map_err(|e| plot_err(path, e))?;
                    }
                    chart
                        .configure_series_labels()
                        .label_font((FONT, 14))
                        .background_style(WHITE.mix(0.85))
                        .border_style(BLACK)
                        .draw()
                        .map_err(|e| plot_err(path, e))?;
                }};
            }
            match (panel.log_x, panel.log_y) {
                (true, true) => draw!(
                    cb.build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
                        .map_err(|e| plot_err(path, e))?
                ),
                (true, false) => draw!(
                    cb.build_cartesian_2d((x0..x1).log_scale(), y0..y1)
                        .map_err(|e| plot_err(path, e))?
                ),
                (false, true) => draw!(
                    cb.build_cartesian_2d(x0..x1, (y0..y1).log_scale())
                        .map_err(|e| plot_err(path, e))?
                ),
                (false, false) => draw!(
                    cb.build_cartesian_2d(x0..x1, y0..y1)
                        .map_err(|e| plot_err(path, e))?
                ),
            }
        }
        root.present().map_err(|e| plot_err(path, e))?;
    }
    save_rgb_buffer(path, buf, w, h)
}

/// Grouped bar chart: one group per `groups` entry, one bar per series, whiskers = std; a strip
/// at the top names the prediction `source` (see [`source_caption`]).
///
/// # Errors
/// Drawing or I/O failure.
pub fn bar_plot(
    path: &Path,
    title: &str,
    source: &str,
    y_label: &str,
    groups: &[String],
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<()> {
    register_fonts();
    let (w, h) = (
        (220 * groups.len().max(1) as u32).max(640),
        480u32 + SOURCE_STRIP_H,
    );
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| plot_err(path, e))?;
        let root = source_strip(path, &root, source)?;
        let ymax = series
            .iter()
            .flat_map(|(_, v)| v.iter().map(|(m, s)| m + s))
            .filter(|x| x.is_finite())
            .fold(0.0f64, f64::max)
            * 1.15;
        let ymax = if ymax > 0.0 { ymax } else { 1.0 };
        let ng = groups.len().max(1);
        let groups_owned: Vec<String> = groups.to_vec();
        let mut chart = ChartBuilder::on(&root)
            .caption(title, (FONT, 20))
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..ng as f64, 0.0..ymax)
            .map_err(|e| plot_err(path, e))?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(ng * 2 + 1)
            .x_label_formatter(&move |x: &f64| {
                let k = x.floor() as usize;
                if (x - k as f64 - 0.5).abs() < 0.01 && k < groups_owned.len() {
                    groups_owned[k].clone()
                } else {
                    String::new()
                }
            })
            .y_desc(y_label)
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 15))
            .draw()
            .map_err(|e| plot_err(path, e))?;
        let ns = series.len().max(1) as f64;
        let bw = 0.8 / ns;
        for (si, (name, vals)) in series.iter().enumerate() {
            let c = series_colour(si);
            let x_of = |g: usize| g as f64 + 0.1 + bw * si as f64;
            chart
                .draw_series(
                    vals.iter()
                        .enumerate()
                        .filter(|(_, v)| v.0.is_finite())
                        .map(|(g, &(m, _))| {
                            Rectangle::new([(x_of(g), 0.0), (x_of(g) + bw * 0.92, m)], c.filled())
                        }),
                )
                .map_err(|e| plot_err(path, e))?
                .label(name.as_str())
                .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], c.filled()));
            chart
                .draw_series(
                    vals.iter()
                        .enumerate()
                        .filter(|(_, v)| v.1 > 0.0 && v.0.is_finite())
                        .map(|(g, &(m, s))| {
                            PathElement::new(
                                vec![
                                    (x_of(g) + bw * 0.46, (m - s).max(0.0)),
                                    (x_of(g) + bw * 0.46, m + s),
                                ],
                                BLACK.stroke_width(2),
                            )
                        }),
                )
                .map_err(|e| plot_err(path, e))?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .label_font((FONT, 14))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(|e| plot_err(path, e))?;
        root.present().map_err(|e| plot_err(path, e))?;
    }
    save_rgb_buffer(path, buf, w, h)
}

fn save_rgb_buffer(path: &Path, buf: Vec<u8>, w: u32, h: u32) -> Result<()> {
    let img = RgbImage::from_raw(w, h, buf).ok_or_else(|| plot_err(path, "buffer size"))?;
    create_parent(path)?;
    moma_io::write_rgb(path, &img)?;
    Ok(())
}

/// One panel of the comparison figure.
#[derive(Debug, Clone)]
pub enum Panel {
    /// An RGB picture.
    Rgb(RgbImage),
    /// A metric map in metres on the row's shared scale.
    Metres(ndarray::Array2<f32>),
    /// A unitless map on its own scale (the raw prediction).
    Unitless(ndarray::Array2<f32>),
    /// A mask picture.
    Mask(Mask),
    /// Nothing.
    Empty,
}

/// One row of the comparison figure: titled panels sharing one colour scale.
#[derive(Debug, Clone)]
pub struct FigureRow {
    /// Panel titles and contents.
    pub panels: Vec<(String, Panel)>,
    /// Colour-bar label (e.g. "depth [m]").
    pub bar_label: String,
    /// Colour scale `[lo, hi]` of the `Metres` panels.
    pub range: (f64, f64),
    /// Multiply tick values by this for display (1000 for mm).
    pub tick_scale: f64,
}

fn resize_nearest(src: &RgbImage, w: u32, h: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| {
        let sx = ((x as f64 + 0.5) * src.width() as f64 / w as f64) as u32;
        let sy = ((y as f64 + 0.5) * src.height() as f64 / h as f64) as u32;
        *src.get_pixel(sx.min(src.width() - 1), sy.min(src.height() - 1))
    })
}

/// Draws rows of panels with one colour bar per row (labelled ticks) and a title; PNG.
///
/// # Errors
/// Drawing or I/O failure.
pub fn comparison_figure(path: &Path, title: &str, rows: &[FigureRow], panel_w: u32) -> Result<()> {
    register_fonts();
    let ncols = rows.iter().map(|r| r.panels.len()).max().unwrap_or(1) as u32;
    let (img_w, img_h) = rows
        .iter()
        .flat_map(|r| r.panels.iter())
        .find_map(|(_, p)| match p {
            Panel::Rgb(i) => Some((i.width(), i.height())),
            Panel::Metres(a) | Panel::Unitless(a) => Some((a.ncols() as u32, a.nrows() as u32)),
            Panel::Mask(m) => Some((m.size().width as u32, m.size().height as u32)),
            Panel::Empty => None,
        })
        .unwrap_or((4, 3));
    let panel_h = (panel_w as f64 * img_h as f64 / img_w as f64).round() as u32;
    let (gap, title_h, head_h, bar_w) = (8u32, 36u32, 24u32, 120u32);
    let w = gap + ncols * (panel_w + gap) + bar_w;
    let row_h = head_h + panel_h + gap;
    let h = title_h + rows.len() as u32 * row_h + gap;
    let mut canvas = RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    // raster content first
    for (ri, row) in rows.iter().enumerate() {
        let y0 = title_h + ri as u32 * row_h + head_h;
        let (lo, hi) = row.range;
        for (ci, (_, p)) in row.panels.iter().enumerate() {
            let x0 = gap + ci as u32 * (panel_w + gap);
            let pic = match p {
                Panel::Rgb(i) => Some(i.clone()),
                Panel::Metres(a) => Some(colourise(a, lo, hi, is_valid_depth)),
                Panel::Unitless(a) => {
                    let plo = quantile(a.iter().copied(), 0.01);
                    let phi = quantile(a.iter().copied(), 0.99);
                    Some(colourise(a, plo, phi, |x| x.is_finite()))
                }
                Panel::Mask(m) => {
                    let (mh, mw) = m.data().dim();
                    Some(RgbImage::from_fn(mw as u32, mh as u32, |u, v| {
                        if m.data()[[v as usize, u as usize]] {
                            image::Rgb([255, 255, 255])
                        } else {
                            image::Rgb([0, 0, 0])
                        }
                    }))
                }
                Panel::Empty => None,
            };
            if let Some(pic) = pic {
                let small = resize_nearest(&pic, panel_w, panel_h);
                image::imageops::replace(&mut canvas, &small, x0 as i64, y0 as i64);
            }
        }
        // colour bar
        let bx = gap + ncols * (panel_w + gap) + 4;
        for y in 0..panel_h {
            let t = 1.0 - y as f64 / (panel_h.max(2) - 1) as f64;
            let c = Colormap::Turbo.rgb(t as f32);
            for x in 0..18 {
                canvas.put_pixel(bx + x, y0 + y, image::Rgb(c));
            }
        }
    }
    let mut buf = canvas.into_raw();
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        let font = (FONT, 16).into_font().color(&BLACK);
        let tfont = (FONT, 20).into_font().color(&BLACK);
        root.draw(&Text::new(title.to_string(), (gap as i32, 8), tfont))
            .map_err(|e| plot_err(path, e))?;
        for (ri, row) in rows.iter().enumerate() {
            let y0 = title_h + ri as u32 * row_h;
            for (ci, (name, _)) in row.panels.iter().enumerate() {
                let x0 = gap + ci as u32 * (panel_w + gap);
                root.draw(&Text::new(
                    name.clone(),
                    (x0 as i32, y0 as i32 + 3),
                    font.clone(),
                ))
                .map_err(|e| plot_err(path, e))?;
            }
            let bx = (gap + ncols * (panel_w + gap) + 4) as i32;
            let py = (y0 + head_h) as i32;
            root.draw(&Text::new(
                row.bar_label.clone(),
                (bx - 4, y0 as i32 + 3),
                font.clone(),
            ))
            .map_err(|e| plot_err(path, e))?;
            let (lo, hi) = row.range;
            let ticks = nice_ticks(lo * row.tick_scale, hi * row.tick_scale, 5);
            for t in ticks {
                let frac = (t / row.tick_scale - lo) / (hi - lo).max(1e-12);
                if !(0.0..=1.0).contains(&frac) {
                    continue;
                }
                let y = py + ((1.0 - frac) * (panel_h as f64 - 1.0)).round() as i32;
                root.draw(&PathElement::new(vec![(bx + 18, y), (bx + 24, y)], BLACK))
                    .map_err(|e| plot_err(path, e))?;
                let prec = if (hi - lo) * row.tick_scale < 0.1 {
                    3
                } else if (hi - lo) * row.tick_scale < 1.0 {
                    2
                } else {
                    0
                }
                .max(tick_prec(lo * row.tick_scale, hi * row.tick_scale));
                root.draw(&Text::new(
                    format!("{t:.prec$}"),
                    (bx + 27, y - 8),
                    (FONT, 14).into_font().color(&BLACK),
                ))
                .map_err(|e| plot_err(path, e))?;
            }
        }
        root.present().map_err(|e| plot_err(path, e))?;
    }
    save_rgb_buffer(path, buf, w, h)
}

fn tick_prec(lo: f64, hi: f64) -> usize {
    let step = nice_step((hi - lo) / 5.0);
    if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    }
}

fn nice_step(raw: f64) -> f64 {
    if raw.is_nan() || raw <= 0.0 || !raw.is_finite() {
        return 1.0;
    }
    let p = 10f64.powf(raw.log10().floor());
    let m = raw / p;
    let k = if m < 1.5 {
        1.0
    } else if m < 3.5 {
        2.0
    } else if m < 7.5 {
        5.0
    } else {
        10.0
    };
    k * p
}

/// "Nice" tick values covering `[lo, hi]`, about `n` of them.
pub fn nice_ticks(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    if hi.is_nan() || lo.is_nan() || hi <= lo {
        return vec![lo];
    }
    let step = nice_step((hi - lo) / n.max(1) as f64);
    let start = (lo / step).ceil() * step;
    let mut v = Vec::new();
    let mut t = start;
    while t <= hi + 1e-9 * step {
        v.push(if t.abs() < 1e-12 * step { 0.0 } else { t });
        t += step;
    }
    v
}

/// The caption line of what `success_prob` is: PROXY, and under which error model (`basis`,
/// e.g. "the calibration's error model"), or "n/a" without one. One text for `moma grasp` and
/// `moma demo`.
pub fn success_prob_caption(basis: Option<&str>) -> String {
    match basis {
        Some(b) => format!("success_prob: PROXY, under {b} (not robot trials)"),
        None => "success_prob: n/a (no error model)".to_string(),
    }
}

/// The lines of a grasp overlay's caption: `title`, then one per grasp, best first, in its rank
/// colour (rank, `success_prob` or "n/a", the planner's score, the position in the camera frame
/// in metres and, for a parallel jaw, the opening), or why there is none.
fn grasp_caption(outcome: &moma_grasp::PlanOutcome, title: &[String]) -> Vec<(String, [u8; 3])> {
    use moma_grasp::Grasp;
    const TITLE: [u8; 3] = [235, 235, 235];
    let n = outcome.grasps.len();
    let mut lines: Vec<(String, [u8; 3])> = title.iter().map(|t| (t.clone(), TITLE)).collect();
    if n == 0 {
        let why = outcome
            .no_grasp_reason
            .as_ref()
            .map_or(String::new(), |r| format!(": {r}"));
        lines.push((format!("no grasp{why}"), TITLE));
    }
    for (rank, g) in outcome.grasps.iter().enumerate() {
        let prob = g
            .success_prob()
            .map_or("n/a".to_string(), |p| format!("{p:.2}"));
        let (at, opening) = match g {
            Grasp::Parallel(p) => (
                p.pose.center_m,
                format!(", opening {:.0} mm", p.pose.width_m * 1000.0),
            ),
            Grasp::Suction(s) => (s.pose.point_m, String::new()),
        };
        lines.push((
            format!(
                "#{}  success_prob {prob}  score {:.3}  at ({:+.3}, {:+.3}, {:+.3}) m{opening}",
                rank + 1,
                g.score(),
                at[0],
                at[1],
                at[2]
            ),
            moma_grasp::render::rank_colour(rank, n),
        ));
    }
    lines
}

/// The picture of planned grasps that moma writes (`moma grasp -o DIR`'s overlay.png, `moma
/// demo`'s grasps/): `background` (the frame's RGB, or its colour-mapped depth) with the grasps
/// drawn outlined in their rank colours ([`moma_grasp::render::rank_colour`]: best green, then
/// yellow to red; strokes thicker from 1 000 px wide), and below it a dark strip that says what
/// the picture is ([`grasp_caption`]: `title`, one line each — the gripper, where the depth
/// came from, SIMULATED where it applies, [`success_prob_caption`] — then one line per grasp in
/// its colour). The text shrinks to the image's width (7 px at the least; longer lines are cut
/// at the border). The image keeps the frame's pixels in its top `height` rows, so the grasps
/// stay where they project. `path` names the file in errors.
///
/// # Errors
/// [`EvalError::Plot`] when the text cannot be drawn.
pub fn grasp_overlay(
    path: &Path,
    mut background: RgbImage,
    k: &moma_core::Intrinsics,
    outcome: &moma_grasp::PlanOutcome,
    gripper: &moma_grasp::Gripper,
    title: &[String],
) -> Result<RgbImage> {
    let (w, h) = background.dimensions();
    let segments = moma_grasp::render::overlay_segments(outcome, gripper);
    moma_io::draw_segments_outlined(&mut background, k, &segments, i64::from(w / 1000));
    register_fonts();
    // DejaVu Sans averages about 0.56 em per character: lines longer than the width are
    // wrapped at spaces (continued two spaces in, in their colour); on images too narrow for
    // 40 characters the text shrinks instead, to 7 px at the least
    let room = f64::from(w.saturating_sub(16)) / 0.56;
    let font_px = (f64::from(w) / 640.0 * 14.0)
        .clamp(12.0, 28.0)
        .min(room / 40.0)
        .max(7.0);
    let per_line = ((room / font_px) as usize).max(1);
    let lines: Vec<(String, [u8; 3])> = grasp_caption(outcome, title)
        .into_iter()
        .flat_map(|(text, colour)| {
            wrap_words(&text, per_line)
                .into_iter()
                .map(move |l| (l, colour))
        })
        .collect();
    let line_h = (font_px * 1.4).ceil() as u32;
    let strip_h = line_h * lines.len() as u32 + line_h / 2;
    const STRIP: [u8; 3] = [28, 28, 28];
    let mut buf: Vec<u8> = STRIP
        .iter()
        .copied()
        .cycle()
        .take(w as usize * strip_h as usize * 3)
        .collect();
    if w > 0 {
        let root = BitMapBackend::with_buffer(&mut buf, (w, strip_h)).into_drawing_area();
        for (i, (text, [r, g, b])) in lines.iter().enumerate() {
            let y = (line_h / 4 + i as u32 * line_h) as i32;
            root.draw(&Text::new(
                text.clone(),
                (8, y),
                (FONT, font_px).into_font().color(&RGBColor(*r, *g, *b)),
            ))
            .map_err(|e| plot_err(path, e))?;
        }
        root.present().map_err(|e| plot_err(path, e))?;
    }
    let strip = RgbImage::from_raw(w, strip_h, buf)
        .ok_or_else(|| plot_err(path, "the caption strip's buffer is not w × h × 3"))?;
    let mut out = RgbImage::new(w, h + strip_h);
    image::imageops::replace(&mut out, &background, 0, 0);
    image::imageops::replace(&mut out, &strip, 0, i64::from(h));
    Ok(out)
}

/// `text` cut at spaces into lines of at most `width` characters (a longer word stands alone),
/// the lines after the first two spaces in.
fn wrap_words(text: &str, width: usize) -> Vec<String> {
    let mut lines: Vec<String> = Vec::new();
    let mut line = String::new();
    for word in text.split(' ') {
        if line.is_empty() || line == "  " {
            line.push_str(word);
        } else if line.chars().count() + 1 + word.chars().count() <= width {
            line.push(' ');
            line.push_str(word);
        } else {
            lines.push(std::mem::take(&mut line));
            line = format!("  {word}");
        }
    }
    lines.push(line);
    lines
}

/// [`grasp_overlay`] written to `path` (PNG, atomically), its caption also in the PNG's
/// `Description` text chunk ([`moma_io::read_png_description`]), one line per caption line.
///
/// # Errors
/// As [`grasp_overlay`]; destination not writable.
pub fn write_grasp_overlay(
    path: &Path,
    background: RgbImage,
    k: &moma_core::Intrinsics,
    outcome: &moma_grasp::PlanOutcome,
    gripper: &moma_grasp::Gripper,
    title: &[String],
) -> Result<()> {
    let img = grasp_overlay(path, background, k, outcome, gripper, title)?;
    let description: Vec<String> = grasp_caption(outcome, title)
        .into_iter()
        .map(|(t, _)| t)
        .collect();
    moma_io::write_rgb_png_described(path, &img, &description.join("\n"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Three suction grasps on a grey 640 × 240 frame: the frame's pixels stay on top (changed
    /// only where the grasps are drawn), and the caption strip below has one line per title
    /// line and per grasp, each grasp's line written in its rank colour.
    #[test]
    fn a_grasp_overlay_keeps_the_frame_and_captions_each_grasp_in_its_colour() {
        use moma_grasp::{Grasp, Gripper, PlanOutcome, SuctionCup, SuctionGrasp, SuctionPose};
        let (w, h) = (640u32, 240u32);
        let k = moma_core::Intrinsics::nominal(moma_core::ImageSize::new(w as usize, h as usize));
        let grasp = |x: f32, p: f32| {
            Grasp::Suction(SuctionGrasp {
                score: 0.5,
                success_prob: Some(p),
                pose: SuctionPose {
                    point_m: [x, 0.0, 0.6],
                    approach: [0.0, 0.0, 1.0],
                },
                base: None,
            })
        };
        let outcome = PlanOutcome {
            grasps: vec![grasp(-0.1, 0.83), grasp(0.0, 0.5), grasp(0.1, 0.17)],
            no_grasp_reason: None,
            candidates: 3,
        };
        let frame = RgbImage::from_pixel(w, h, image::Rgb([128, 128, 128]));
        let title = ["line one".to_string(), "line two".to_string()];
        let gripper = Gripper::Suction(SuctionCup::default());
        let out = grasp_overlay(Path::new("x.png"), frame, &k, &outcome, &gripper, &title).unwrap();
        assert_eq!(out.width(), w);
        assert!(out.height() > h);
        let changed = (0..h)
            .flat_map(|v| (0..w).map(move |u| (u, v)))
            .filter(|&(u, v)| out.get_pixel(u, v).0 != [128, 128, 128])
            .count();
        assert!(changed > 0 && changed < (w * h / 20) as usize, "{changed}");
        // 5 lines (2 title, 3 grasps) of equal height, half a line of margin
        let line_h = (h..out.height()).len() as f64 / 5.5;
        // each grasp's text (anti-aliased on the strip's ground): its pixels far from the ground
        // are nearest its own rank colour of the three
        let colours: Vec<[u8; 3]> = (0..3)
            .map(|r| moma_grasp::render::rank_colour(r, 3))
            .collect();
        let dist = |a: [u8; 3], b: [u8; 3]| -> i32 {
            (0..3)
                .map(|i| (i32::from(a[i]) - i32::from(b[i])).pow(2))
                .sum()
        };
        for rank in 0..3 {
            let top = h as f64 + line_h * (2 + rank) as f64;
            let rows = top as u32..(top + line_h) as u32;
            let text: Vec<[u8; 3]> = rows
                .flat_map(|v| (0..w).map(move |u| (u, v)))
                .map(|(u, v)| out.get_pixel(u, v).0)
                .filter(|p| dist(*p, [28, 28, 28]) > 150 * 150)
                .collect();
            assert!(text.len() > 20, "rank {rank}: {} text pixels", text.len());
            let mut votes = [0usize; 3];
            for p in &text {
                let nearest = (0..3).min_by_key(|&r| dist(*p, colours[r])).unwrap();
                votes[nearest] += 1;
            }
            let top_vote = (0..3).max_by_key(|&r| votes[r]).unwrap();
            assert_eq!(top_vote, rank, "votes {votes:?}");
        }
    }

    #[test]
    fn caption_lines_wrap_at_spaces_within_the_width() {
        assert_eq!(wrap_words("short line", 40), vec!["short line"]);
        let text = "success_prob: PROXY, under the calibration's error model (not robot trials)";
        let lines = wrap_words(text, 30);
        assert!(lines.len() > 1 && lines.iter().all(|l| l.chars().count() <= 30));
        assert!(lines[1..].iter().all(|l| l.starts_with("  ")));
        let rejoined: Vec<&str> = lines.iter().flat_map(|l| l.split_whitespace()).collect();
        assert_eq!(rejoined, text.split_whitespace().collect::<Vec<_>>());
        // the double spaces of a grasp's line stay; a word longer than the width stands alone
        assert_eq!(wrap_words("#1  p 0.83", 40), vec!["#1  p 0.83"]);
        assert_eq!(wrap_words("abcdefgh x", 4), vec!["abcdefgh", "  x"]);
    }

    #[test]
    fn ticks_are_nice() {
        assert_eq!(
            nice_ticks(0.0, 10.0, 5),
            vec![0.0, 2.0, 4.0, 6.0, 8.0, 10.0]
        );
        let t = nice_ticks(0.53, 0.81, 5);
        assert!(t.len() >= 3 && t[0] >= 0.53 && *t.last().unwrap() <= 0.81);
    }

    #[test]
    fn figures_colour_with_moma_io() {
        // Same pixels as `moma align --colormap turbo` over the same range, grey where invalid.
        let a = ndarray::array![[1.0f32, 1.5, 2.0], [f32::NAN, 0.0, 3.0]];
        let fig = colourise(&a, 1.0, 2.0, is_valid_depth);
        let io = moma_io::colourise(a.view(), Colormap::Turbo, 1.0, 2.0, is_valid_depth);
        for (x, y, p) in fig.enumerate_pixels() {
            if is_valid_depth(a[[y as usize, x as usize]]) {
                assert_eq!(p, io.get_pixel(x, y));
            } else {
                assert_eq!(p.0, INVALID_RGB);
            }
        }
        // published Turbo entries 0, 128 and 255
        assert_eq!(fig.get_pixel(0, 0).0, [48, 18, 59]);
        assert_eq!(fig.get_pixel(1, 0).0, [164, 252, 60]);
        assert_eq!(fig.get_pixel(2, 0).0, [122, 4, 3]);
    }

    #[test]
    fn plots_render_with_embedded_font() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("l.png");
        line_plot(
            &p,
            "SIMULATED predictions (test)",
            &[LinePanel {
                title: "t".into(),
                x_label: "n".into(),
                y_label: "mm".into(),
                log_x: true,
                log_y: false,
                series: vec![Series {
                    name: "a".into(),
                    points: vec![(20.0, 3.0, 0.5), (100.0, 2.0, 0.2), (1000.0, 1.5, 0.1)],
                }],
            }],
            500,
            400,
        )
        .unwrap();
        assert!(p.exists());
        let b = dir.path().join("b.png");
        bar_plot(
            &b,
            "bars",
            "predictions: test",
            "MAE mm",
            &["x".into(), "y".into()],
            &[
                ("s1".into(), vec![(1.0, 0.1), (2.0, 0.2)]),
                ("s2".into(), vec![(1.5, 0.0), (0.5, 0.1)]),
            ],
        )
        .unwrap();
        assert!(b.exists());
    }

    /// Dark pixels in the source strip at the top of a plot.
    fn ink_in_source_strip(path: &Path) -> usize {
        let img = moma_io::read_rgb(path).unwrap();
        (0..SOURCE_STRIP_H)
            .flat_map(|y| (0..img.width()).map(move |x| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y).0.iter().all(|&c| c < 128))
            .count()
    }

    #[test]
    fn plots_name_their_prediction_source() {
        assert_eq!(
            source_caption("simulated inverse-depth (seed 0)", true),
            "SIMULATED predictions (simulated inverse-depth (seed 0))"
        );
        assert_eq!(
            source_caption("vits (random weights)", false),
            "predictions: vits (random weights)"
        );
        let dir = tempfile::tempdir().unwrap();
        let bars = |name: &str, source: &str| {
            let p = dir.path().join(name);
            bar_plot(
                &p,
                "b",
                source,
                "MAE mm",
                &["x".into()],
                &[("s".into(), vec![(1.0, 0.1)])],
            )
            .unwrap();
            p
        };
        // the strip holds the text and nothing else
        assert_eq!(ink_in_source_strip(&bars("empty.png", "")), 0);
        assert!(ink_in_source_strip(&bars("sim.png", "SIMULATED predictions (x)")) > 50);
        let p = dir.path().join("line.png");
        let panel = LinePanel {
            title: "t".into(),
            x_label: "n".into(),
            y_label: "mm".into(),
            log_x: false,
            log_y: false,
            series: vec![Series {
                name: "a".into(),
                points: vec![(1.0, 1.0, 0.0), (2.0, 2.0, 0.0)],
            }],
        };
        line_plot(&p, "", std::slice::from_ref(&panel), 300, 200).unwrap();
        assert_eq!(ink_in_source_strip(&p), 0);
        line_plot(&p, "predictions: vits", &[panel], 300, 200).unwrap();
        assert!(ink_in_source_strip(&p) > 50);
    }
}
