//! Colour-mapped depth images for people: turbo and viridis, value range recorded in the PNG.

use std::path::Path;

use image::{Rgb, RgbImage};
use moma_core::{CoreError, MetricDepth, is_valid_depth};
use ndarray::ArrayView2;
use serde::{Deserialize, Serialize};

use crate::atomic::atomic_write;
use crate::error::{IoError, Result};
use crate::png_util::{PngPixels, encode_png, read_png_texts};

#[path = "colormap_tables.rs"]
mod tables;

/// A colour map from `t ∈ [0, 1]` to 8-bit sRGB, from the published 256-entry tables (as shipped by
/// matplotlib): `t` picks entry `floor(256·t)` (clipped to `0..=255`, matplotlib's rule for a
/// `ListedColormap`) and each component `x ∈ [0, 1]` becomes `round(255·x)`. See
/// [`Colormap::rgb`] and [`colormap_index`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Colormap {
    /// Google's Turbo (Mikhailov 2019), the published 256-entry table: blue (near / small) to red
    /// (far / large).
    #[default]
    Turbo,
    /// Matplotlib's viridis (van der Walt & Smith 2015), its 256-entry table: dark purple to
    /// yellow, perceptually uniform.
    Viridis,
}

/// Number of entries of each colour table.
pub const COLORMAP_ENTRIES: usize = 256;

/// The table index of `t`, matplotlib's rule for a 256-entry `ListedColormap`:
/// `i = floor(256·t)`, with `t = 1` (and anything above) the last entry and `t < 0` the first;
/// NaN gives entry 0.
pub fn colormap_index(t: f32) -> usize {
    if t.is_nan() || t <= 0.0 {
        return 0;
    }
    // f64: 256·t is exact for every f32 t, so the bin edges k/256 fall where they should.
    let i = (f64::from(t) * COLORMAP_ENTRIES as f64).floor();
    if i >= (COLORMAP_ENTRIES - 1) as f64 {
        COLORMAP_ENTRIES - 1
    } else {
        i as usize
    }
}

/// A table component in `[0, 1]` as an 8-bit value: `round(255·x)`.
fn to_u8(x: f64) -> u8 {
    (x.clamp(0.0, 1.0) * 255.0).round() as u8
}

impl Colormap {
    /// The published table entry `index` (`0..256`, clamped), sRGB components in `[0, 1]`.
    pub fn entry(self, index: usize) -> [f64; 3] {
        let i = index.min(COLORMAP_ENTRIES - 1);
        match self {
            Self::Turbo => tables::TURBO[i],
            Self::Viridis => tables::VIRIDIS[i],
        }
    }

    /// The 8-bit colour of `t ∈ [0, 1]`: table entry [`colormap_index`]`(t)` (matplotlib's
    /// `floor(256·t)`, clipped), each component `round(255·x)`. Values outside `[0, 1]` are
    /// clamped; NaN gives the first colour.
    pub fn rgb(self, t: f32) -> [u8; 3] {
        self.entry(colormap_index(t)).map(to_u8)
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
    colourise_with(values, colormap, min, max, is_valid, [0, 0, 0])
}

/// As [`colourise`], with pixels where `is_valid(v)` is false painted `invalid_rgb`.
/// The one colouriser of the workspace: `moma align --colormap`, `moma predict` and the
/// evaluation figures all come here.
pub fn colourise_with(
    values: ArrayView2<'_, f32>,
    colormap: Colormap,
    min: f32,
    max: f32,
    is_valid: impl Fn(f32) -> bool,
    invalid_rgb: [u8; 3],
) -> RgbImage {
    let (h, w) = values.dim();
    let span = if max > min {
        max - min
    } else {
        f32::MIN_POSITIVE
    };
    let mut img = RgbImage::from_pixel(w as u32, h as u32, Rgb(invalid_rgb));
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
    write_colormap_png(path.as_ref(), depth, colormap, range, "depth")
}

/// Writes a colour-mapped PNG of a per-pixel σ map of the depth error (metres, NaN = no depth;
/// `moma align --sigma-map`), as [`write_depth_colormap`] does a depth map: the same range
/// chunks (σ in metres), described as a σ map.
///
/// # Errors
/// As [`write_depth_colormap`].
pub fn write_sigma_colormap(
    path: impl AsRef<Path>,
    sigma: &MetricDepth,
    colormap: Colormap,
    range: DepthRange,
) -> Result<ColourScale> {
    write_colormap_png(
        path.as_ref(),
        sigma,
        colormap,
        range,
        "sigma (1 SD) of the depth error",
    )
}

/// A colour-mapped PNG of a map in metres; `what` names the map in its description chunk.
fn write_colormap_png(
    path: &Path,
    depth: &MetricDepth,
    colormap: Colormap,
    range: DepthRange,
    what: &str,
) -> Result<ColourScale> {
    let (img, scale) =
        colourise_depth(depth, colormap, range).map_err(|e| IoError::core(path, e))?;
    let texts = [
        (TEXT_COLORMAP, scale.colormap.name().to_string()),
        (TEXT_MIN_M, scale.min_m.to_string()),
        (TEXT_MAX_M, scale.max_m.to_string()),
        (
            "Description",
            format!(
                "moma {what}, colour map {} from {} m to {} m (clamped); black = no depth",
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

    /// Published entries (matplotlib `_turbo_data` / `_viridis_data`, i.e. Mikhailov's Turbo table
    /// and the viridis table), written out here, and their 8-bit values `round(255·x)` worked out
    /// by hand from them.
    const TURBO_PUBLISHED: [(usize, [f64; 3], [u8; 3]); 6] = [
        (0, [0.18995, 0.07176, 0.23217], [48, 18, 59]),
        (1, [0.19483, 0.08339, 0.26149], [50, 21, 67]),
        (64, [0.15844, 0.73551, 0.92305], [40, 188, 235]),
        (128, [0.64362, 0.98999, 0.23356], [164, 252, 60]),
        (192, [0.98360, 0.49291, 0.12849], [251, 126, 33]),
        (255, [0.47960, 0.01583, 0.01055], [122, 4, 3]),
    ];
    const VIRIDIS_PUBLISHED: [(usize, [f64; 3], [u8; 3]); 6] = [
        (0, [0.267004, 0.004874, 0.329415], [68, 1, 84]), // #440154
        (1, [0.268510, 0.009605, 0.335427], [68, 2, 86]),
        (64, [0.229739, 0.322361, 0.545706], [59, 82, 139]),
        (128, [0.127568, 0.566949, 0.550556], [33, 145, 140]), // #21918c
        (192, [0.369214, 0.788888, 0.382914], [94, 201, 98]),
        (255, [0.993248, 0.906157, 0.143936], [253, 231, 37]), // #fde725
    ];

    /// `t` in the middle of bin `i` of 256.
    fn mid(i: usize) -> f32 {
        (i as f32 + 0.5) / 256.0
    }

    #[test]
    fn tables_equal_the_published_values_exactly() {
        for (cmap, published) in [
            (Colormap::Turbo, TURBO_PUBLISHED),
            (Colormap::Viridis, VIRIDIS_PUBLISHED),
        ] {
            for (i, floats, bytes) in published {
                assert_eq!(cmap.entry(i), floats, "{cmap} entry {i}");
                assert_eq!(cmap.rgb(mid(i)), bytes, "{cmap} colour of bin {i}");
            }
        }
    }

    #[test]
    fn whole_tables_match_matplotlib_checksums() {
        // Σ over all 256 entries of r+g+b, and Σ i·(r + 2g + 3b), computed with matplotlib 3.11.2
        // from `_turbo_data` / `_viridis_data`: any changed, swapped or missing entry shows.
        for (cmap, sum, weighted) in [
            (Colormap::Turbo, 392.575, 80_837.046_23),
            (Colormap::Viridis, 331.700_518, 95_412.112_106),
        ] {
            let (mut s, mut w) = (0.0f64, 0.0f64);
            for i in 0..COLORMAP_ENTRIES {
                let [r, g, b] = cmap.entry(i);
                s += r + g + b;
                w += i as f64 * (r + 2.0 * g + 3.0 * b);
            }
            assert!((s - sum).abs() < 1e-9, "{cmap}: Σ = {s}");
            assert!((w - weighted).abs() < 1e-7, "{cmap}: Σ i·(r+2g+3b) = {w}");
        }
    }

    #[test]
    fn index_rule_is_matplotlibs_floor_256t() {
        assert_eq!(colormap_index(0.0), 0);
        assert_eq!(colormap_index(1.0 / 256.0 - 1e-6), 0);
        assert_eq!(colormap_index(1.0 / 256.0), 1);
        assert_eq!(colormap_index(0.5), 128);
        assert_eq!(colormap_index(127.99 / 256.0), 127);
        assert_eq!(colormap_index(255.0 / 256.0), 255);
        assert_eq!(colormap_index(1.0), 255);
        // clamping and NaN
        assert_eq!(colormap_index(-3.0), 0);
        assert_eq!(colormap_index(7.0), 255);
        assert_eq!(colormap_index(f32::NAN), 0);
        assert_eq!(Colormap::Turbo.rgb(0.0), [48, 18, 59]);
        assert_eq!(Colormap::Turbo.rgb(0.5), [164, 252, 60]);
        assert_eq!(Colormap::Turbo.rgb(1.0), [122, 4, 3]);
        assert_eq!(Colormap::Viridis.rgb(127.99 / 256.0), [33, 144, 141]);
        assert_eq!(Colormap::Turbo.rgb(-3.0), Colormap::Turbo.rgb(0.0));
        assert_eq!(Colormap::Turbo.rgb(7.0), Colormap::Turbo.rgb(1.0));
        assert_eq!(Colormap::Turbo.rgb(f32::NAN), Colormap::Turbo.rgb(0.0));
    }

    #[test]
    fn colourise_with_paints_invalid_pixels() {
        let v = array![[0.0f32, f32::NAN, 10.0]];
        let img = colourise_with(
            v.view(),
            Colormap::Turbo,
            0.0,
            10.0,
            f32::is_finite,
            [1, 2, 3],
        );
        assert_eq!(img.get_pixel(0, 0).0, [48, 18, 59]);
        assert_eq!(img.get_pixel(1, 0).0, [1, 2, 3]);
        assert_eq!(img.get_pixel(2, 0).0, [122, 4, 3]);
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
