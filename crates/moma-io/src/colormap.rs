//! Colour-mapped depth images for people: turbo and viridis, value range recorded in the PNG.

use std::path::Path;

use image::{Rgb, RgbImage};
use moma_core::{CoreError, MetricDepth, is_valid_depth};
use ndarray::ArrayView2;
use serde::{Deserialize, Serialize};

use crate::atomic::atomic_write;
use crate::error::{IoError, Result};
use crate::png_util::{PngPixels, encode_png, read_png_texts};

/// A colour map from `t ∈ [0, 1]` to 8-bit sRGB.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Colormap {
    /// Google's Turbo (Mikhailov 2019): blue (near / small) to red (far / large).
    #[default]
    Turbo,
    /// Matplotlib's viridis (van der Walt & Smith 2015): dark purple to yellow, perceptually uniform.
    Viridis,
}

// Turbo: polynomial approximation by Ruofei Du (Google), published with the colormap,
// https://gist.github.com/mikhailov-work/0d177465a8151eb6ede1768d51d476c7 (Apache-2.0);
// see https://ai.googleblog.com/2019/08/turbo-improved-rainbow-colormap-for.html.
// r(x) = Σ_k c_k x^k, k = 0..5, per channel.
const TURBO: [[f64; 6]; 3] = [
    [
        0.135_721_38,
        4.615_392_60,
        -42.660_322_58,
        132.131_082_34,
        -152.942_393_96,
        59.286_379_43,
    ],
    [
        0.091_402_61,
        2.194_188_39,
        4.842_966_58,
        -14.185_033_33,
        4.277_298_57,
        2.829_566_04,
    ],
    [
        0.106_673_30,
        12.641_946_08,
        -60.582_048_36,
        110.362_767_71,
        -89.903_109_12,
        27.348_249_73,
    ],
];

// Viridis: degree-6 least-squares polynomial fit by Matt Zucker,
// https://www.shadertoy.com/view/WlfXRN (fitted to matplotlib's viridis LUT, CC0).
// c_k per channel (r, g, b), k = 0..6.
const VIRIDIS: [[f64; 7]; 3] = [
    [
        0.277_727_327_223_417_7,
        0.105_093_043_108_577_4,
        -0.330_861_828_725_556_3,
        -4.634_230_498_983_486,
        6.228_269_936_347_081,
        4.776_384_997_670_288,
        -5.435_455_855_934_631,
    ],
    [
        0.005_407_344_544_966_578,
        1.404_613_529_898_575,
        0.214_847_559_468_213,
        -5.799_100_973_351_585,
        14.179_933_366_805_09,
        -13.745_145_377_746_01,
        4.645_852_612_178_535,
    ],
    [
        0.334_099_805_335_306_1,
        1.384_590_162_594_685,
        0.095_095_163_028_236_59,
        -19.332_440_956_279_87,
        56.690_552_600_681_05,
        -65.353_032_633_372_34,
        26.312_435_249_583_2,
    ],
];

fn horner(c: &[f64], x: f64) -> f64 {
    c.iter().rev().fold(0.0, |acc, &k| acc * x + k)
}

fn to_u8(v: f64) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

impl Colormap {
    /// The colour of `t`, clamped to `[0, 1]` (NaN → 0).
    pub fn rgb(self, t: f32) -> [u8; 3] {
        let x = if t.is_nan() {
            0.0
        } else {
            f64::from(t.clamp(0.0, 1.0))
        };
        let eval = |c: &[f64]| to_u8(horner(c, x));
        match self {
            Self::Turbo => [eval(&TURBO[0]), eval(&TURBO[1]), eval(&TURBO[2])],
            Self::Viridis => [eval(&VIRIDIS[0]), eval(&VIRIDIS[1]), eval(&VIRIDIS[2])],
        }
    }

    /// Lower-case name (`turbo`, `viridis`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Turbo => "turbo",
            Self::Viridis => "viridis",
        }
    }
}

impl std::fmt::Display for Colormap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Colormap {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self, CoreError> {
        match s.to_ascii_lowercase().as_str() {
            "turbo" => Ok(Self::Turbo),
            "viridis" => Ok(Self::Viridis),
            other => Err(CoreError::InvalidParameter(format!(
                "unknown colour map '{other}' (expected 'turbo' or 'viridis')"
            ))),
        }
    }
}

/// How the value range of a colour map is chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DepthRange {
    /// A fixed range in metres: `min_m` maps to the first colour, `max_m` to the last.
    Fixed {
        /// Depth at colour 0, metres.
        min_m: f32,
        /// Depth at colour 1, metres.
        max_m: f32,
    },
    /// Robust automatic range: the `low` and `high` percentiles (0–100) of the valid depths
    /// (nearest rank), so that a few outliers do not wash out the image.
    Percentile {
        /// Lower percentile, e.g. 2.
        low: f32,
        /// Upper percentile, e.g. 98.
        high: f32,
    },
}

impl Default for DepthRange {
    /// The 2nd to 98th percentile of the valid depths.
    fn default() -> Self {
        Self::Percentile {
            low: 2.0,
            high: 98.0,
        }
    }
}

/// A colour map with its value range: what a colour in a colour-mapped image means.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ColourScale {
    /// The colour map.
    pub colormap: Colormap,
    /// Depth at the first colour, metres (smaller depths are clamped to it).
    pub min_m: f32,
    /// Depth at the last colour, metres (larger depths are clamped to it).
    pub max_m: f32,
}

/// The `p`-th percentile (0–100, nearest rank) of `sorted` (non-empty, ascending).
fn percentile(sorted: &[f32], p: f32) -> f32 {
    let p = p.clamp(0.0, 100.0);
    let idx = ((p / 100.0) * (sorted.len() - 1) as f32).round() as usize;
    sorted[idx.min(sorted.len() - 1)]
}

/// Resolves `range` for `depth`: a fixed range is checked; a percentile range is computed over
/// the valid pixels. A constant map gets `max_m = min_m + 1 mm`; a map without valid pixels gets
/// `[0, 1] m` (the image is then all black).
///
/// # Errors
/// [`CoreError::InvalidParameter`] for a fixed range that is not finite with `min_m < max_m`,
/// or percentiles outside `0 ≤ low < high ≤ 100`.
pub fn resolve_range(
    depth: &MetricDepth,
    colormap: Colormap,
    range: DepthRange,
) -> Result<ColourScale, CoreError> {
    let (min_m, max_m) = match range {
        DepthRange::Fixed { min_m, max_m } => {
            if !(min_m.is_finite() && max_m.is_finite() && min_m < max_m) {
                return Err(CoreError::InvalidParameter(format!(
                    "colour-map range [{min_m}, {max_m}] m must be finite with min < max"
                )));
            }
            (min_m, max_m)
        }
        DepthRange::Percentile { low, high } => {
            if !(0.0..=100.0).contains(&low) || !(0.0..=100.0).contains(&high) || low >= high {
                return Err(CoreError::InvalidParameter(format!(
                    "colour-map percentiles {low}..{high} must satisfy 0 <= low < high <= 100"
                )));
            }
            let mut valid: Vec<f32> = depth
                .depth_m
                .iter()
                .copied()
                .filter(|&z| is_valid_depth(z))
                .collect();
            if valid.is_empty() {
                (0.0, 1.0)
            } else {
                valid.sort_unstable_by(f32::total_cmp);
                let (lo, hi) = (percentile(&valid, low), percentile(&valid, high));
                if hi > lo { (lo, hi) } else { (lo, lo + 1e-3) }
            }
        }
    };
    Ok(ColourScale {
        colormap,
        min_m,
        max_m,
    })
}

/// Colours `values` with `colormap` over `[min, max]` (any unit): `t = (v − min)/(max − min)`
/// clamped to `[0, 1]`; pixels where `is_valid(v)` is false are black.
pub fn colourise(
    values: ArrayView2<'_, f32>,
    colormap: Colormap,
    min: f32,
    max: f32,
    is_valid: impl Fn(f32) -> bool,
) -> RgbImage {
    let (h, w) = values.dim();
    let span = if max > min {
        max - min
    } else {
        f32::MIN_POSITIVE
    };
    let mut img = RgbImage::new(w as u32, h as u32);
    for ((v, u), &z) in values.indexed_iter() {
        if is_valid(z) {
            img.put_pixel(u as u32, v as u32, Rgb(colormap.rgb((z - min) / span)));
        }
    }
    img
}

/// Colours a metric depth map (metres) for people: invalid pixels (NaN, ±inf, ≤ 0) black.
///
/// # Errors
/// As [`resolve_range`].
pub fn colourise_depth(
    depth: &MetricDepth,
    colormap: Colormap,
    range: DepthRange,
) -> Result<(RgbImage, ColourScale), CoreError> {
    let scale = resolve_range(depth, colormap, range)?;
    let img = colourise(
        depth.depth_m.view(),
        colormap,
        scale.min_m,
        scale.max_m,
        is_valid_depth,
    );
    Ok((img, scale))
}

/// `tEXt` keyword holding the colour map name.
pub const TEXT_COLORMAP: &str = "moma:colormap";
/// `tEXt` keyword holding the depth at the first colour, metres.
pub const TEXT_MIN_M: &str = "moma:min_m";
/// `tEXt` keyword holding the depth at the last colour, metres.
pub const TEXT_MAX_M: &str = "moma:max_m";

/// Writes a colour-mapped depth PNG (8-bit RGB) atomically and returns its [`ColourScale`].
/// The scale is recorded in the PNG as `tEXt` chunks `moma:colormap`, `moma:min_m`, `moma:max_m`
/// (metres, shortest round-trip decimal) and a human-readable `Description`; read it back with
/// [`read_colour_scale`].
///
/// # Errors
/// [`IoError::Core`] for an invalid range; destination not writable; an empty map.
pub fn write_depth_colormap(
    path: impl AsRef<Path>,
    depth: &MetricDepth,
    colormap: Colormap,
    range: DepthRange,
) -> Result<ColourScale> {
    let path = path.as_ref();
    let (img, scale) =
        colourise_depth(depth, colormap, range).map_err(|e| IoError::core(path, e))?;
    let texts = [
        (TEXT_COLORMAP, scale.colormap.name().to_string()),
        (TEXT_MIN_M, scale.min_m.to_string()),
        (TEXT_MAX_M, scale.max_m.to_string()),
        (
            "Description",
            format!(
                "moma depth, colour map {} from {} m to {} m (clamped); black = no depth",
                scale.colormap, scale.min_m, scale.max_m
            ),
        ),
    ];
    let (w, h) = (img.width() as usize, img.height() as usize);
    atomic_write(path, |out| {
        encode_png(out, path, w, h, PngPixels::Rgb8(img.as_raw()), &texts)
    })?;
    Ok(scale)
}

/// Reads the [`ColourScale`] recorded by [`write_depth_colormap`]; `None` when the PNG has no
/// (or incomplete) moma colour-map chunks.
///
/// # Errors
/// Unreadable or corrupt PNG; [`IoError::Invalid`] for malformed values in the chunks.
pub fn read_colour_scale(path: impl AsRef<Path>) -> Result<Option<ColourScale>> {
    let path = path.as_ref();
    let texts = read_png_texts(path)?;
    let get = |k: &str| {
        texts
            .iter()
            .find(|(key, _)| key == k)
            .map(|(_, v)| v.as_str())
    };
    let (Some(c), Some(lo), Some(hi)) = (get(TEXT_COLORMAP), get(TEXT_MIN_M), get(TEXT_MAX_M))
    else {
        return Ok(None);
    };
    let bad = |what: &str, v: &str| {
        IoError::invalid(path, format!("malformed colour-map chunk {what} = '{v}'"))
    };
    Ok(Some(ColourScale {
        colormap: c.parse().map_err(|_| bad(TEXT_COLORMAP, c))?,
        min_m: lo.parse().map_err(|_| bad(TEXT_MIN_M, lo))?,
        max_m: hi.parse().map_err(|_| bad(TEXT_MAX_M, hi))?,
    }))
}

/// A horizontal colour bar, `width × height` pixels: column `x` shows `t = x / (width − 1)`
/// (the minimum on the left, the maximum on the right). Labels are the caller's job.
pub fn colour_bar(colormap: Colormap, width: u32, height: u32) -> RgbImage {
    let denom = width.saturating_sub(1).max(1) as f32;
    RgbImage::from_fn(width, height, |x, _| {
        let t = if width == 1 { 0.5 } else { x as f32 / denom };
        Rgb(colormap.rgb(t))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::array;

    fn close(a: [u8; 3], b: [u8; 3], tol: i16) -> bool {
        a.iter()
            .zip(b)
            .all(|(&x, y)| (i16::from(x) - i16::from(y)).abs() <= tol)
    }

    #[test]
    fn viridis_matches_matplotlib_anchors() {
        // matplotlib viridis LUT entries 0, 128, 255: #440154, #21918c, #fde725.
        assert!(
            close(Colormap::Viridis.rgb(0.0), [68, 1, 84], 4),
            "{:?}",
            Colormap::Viridis.rgb(0.0)
        );
        assert!(close(
            Colormap::Viridis.rgb(128.0 / 255.0),
            [33, 145, 140],
            4
        ));
        assert!(
            close(Colormap::Viridis.rgb(1.0), [253, 231, 37], 4),
            "{:?}",
            Colormap::Viridis.rgb(1.0)
        );
    }

    #[test]
    fn turbo_matches_lut_anchors() {
        // Turbo LUT (Mikhailov's gist, turbo_srgb_floats) entries 0, 128, 255:
        // (0.18995, 0.07176, 0.23217), (0.64362, 0.98999, 0.23356), (0.47960, 0.01583, 0.01055).
        // The published polynomial stays within ~32/255 of the LUT, worst at the dark ends.
        let lut = |c: [f64; 3]| c.map(|v| (v * 255.0).round() as u8);
        let t = Colormap::Turbo;
        assert!(
            close(t.rgb(0.0), lut([0.18995, 0.07176, 0.23217]), 35),
            "{:?}",
            t.rgb(0.0)
        );
        assert!(
            close(t.rgb(128.0 / 255.0), lut([0.64362, 0.98999, 0.23356]), 24),
            "{:?}",
            t.rgb(0.5)
        );
        assert!(
            close(t.rgb(1.0), lut([0.47960, 0.01583, 0.01055]), 25),
            "{:?}",
            t.rgb(1.0)
        );
        // Clamping and NaN.
        assert_eq!(Colormap::Turbo.rgb(-3.0), Colormap::Turbo.rgb(0.0));
        assert_eq!(Colormap::Turbo.rgb(7.0), Colormap::Turbo.rgb(1.0));
        assert_eq!(Colormap::Turbo.rgb(f32::NAN), Colormap::Turbo.rgb(0.0));
    }

    #[test]
    fn percentile_range_and_black_invalid() {
        let d = MetricDepth::new(array![[1.0f32, 2.0, 3.0], [f32::NAN, 0.0, 100.0]]);
        let s = resolve_range(
            &d,
            Colormap::Turbo,
            DepthRange::Percentile {
                low: 0.0,
                high: 75.0,
            },
        )
        .unwrap();
        assert_eq!((s.min_m, s.max_m), (1.0, 3.0));
        let (img, _) = colourise_depth(
            &d,
            Colormap::Viridis,
            DepthRange::Fixed {
                min_m: 1.0,
                max_m: 3.0,
            },
        )
        .unwrap();
        assert_eq!(img.get_pixel(0, 1).0, [0, 0, 0]);
        assert_eq!(img.get_pixel(1, 1).0, [0, 0, 0]);
        assert_eq!(img.get_pixel(0, 0).0, Colormap::Viridis.rgb(0.0));
        assert_eq!(img.get_pixel(2, 1).0, Colormap::Viridis.rgb(1.0));
        assert!(
            resolve_range(
                &d,
                Colormap::Turbo,
                DepthRange::Fixed {
                    min_m: 2.0,
                    max_m: 2.0
                }
            )
            .is_err()
        );
        let flat = MetricDepth::new(array![[2.0f32, 2.0]]);
        let s = resolve_range(&flat, Colormap::Turbo, DepthRange::default()).unwrap();
        assert!(s.max_m > s.min_m);
    }

    #[test]
    fn colour_bar_runs_min_to_max() {
        let bar = colour_bar(Colormap::Turbo, 256, 10);
        assert_eq!(bar.dimensions(), (256, 10));
        assert_eq!(bar.get_pixel(0, 5).0, Colormap::Turbo.rgb(0.0));
        assert_eq!(bar.get_pixel(255, 9).0, Colormap::Turbo.rgb(1.0));
    }
}
