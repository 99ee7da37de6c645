//! Typed image buffers: sizes, masks, predictions (unitless) and metric depth (metres).
//!
//! All maps are `ndarray::Array2<f32>` with shape `(height, width)`, row-major; pixel
//! `(u, v)` = (column, row) is element `[[v, u]]`.

use ndarray::{Array2, ArrayView2};
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};

/// Width and height of an image in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageSize {
    /// Number of columns (pixels).
    pub width: usize,
    /// Number of rows (pixels).
    pub height: usize,
}

impl ImageSize {
    /// Creates a size; `width` and `height` in pixels.
    pub const fn new(width: usize, height: usize) -> Self {
        Self { width, height }
    }
    /// Number of pixels, `width * height`, saturating at `usize::MAX` (a size read from a file
    /// may claim any width and height; a wrapped product could pass a size limit).
    pub const fn pixels(&self) -> usize {
        self.width.saturating_mul(self.height)
    }
    /// Whether the size is non-empty and at most [`MAX_IMAGE_PIXELS`]: the bound every size read
    /// from a file must meet before anything is allocated for it.
    pub const fn is_within_limits(&self) -> bool {
        let p = self.pixels();
        p > 0 && p <= MAX_IMAGE_PIXELS
    }
    /// The size of an `(height, width)` array.
    pub fn of<T>(a: &ArrayView2<'_, T>) -> Self {
        Self::new(a.ncols(), a.nrows())
    }
    /// `ndarray` shape `(height, width)`.
    pub const fn shape(&self) -> (usize, usize) {
        (self.height, self.width)
    }
    /// Errors with [`CoreError::SizeMismatch`] unless `got == self`.
    pub fn expect_eq(&self, what: &'static str, got: ImageSize) -> Result<()> {
        if *self == got {
            Ok(())
        } else {
            Err(CoreError::SizeMismatch {
                what,
                expected: *self,
                got,
            })
        }
    }
}

impl std::fmt::Display for ImageSize {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}x{} (WxH)", self.width, self.height)
    }
}

/// Largest image accepted anywhere in moma, pixels: 2^26 = 67 108 864 (e.g. 8192 × 8192; eight
/// times a 4K frame; a float32 map of this size takes 256 MiB). The one bound: decoders and
/// file readers (`moma_io::MAX_IMAGE_PIXELS` is this value), calibration and anchor-store sizes
/// refuse larger sizes before allocating. (It was 2^28 here and 2^26 in the decoders, so a
/// calibration could claim a size no image file of it could have.)
pub const MAX_IMAGE_PIXELS: usize = 1 << 26;

/// 8-connected components of `pixels` (row-major, `size`): `(labels, counts)` with label 0 for
/// background and labels `1..=counts.len()` in raster order of each component's first pixel;
/// `counts[l - 1]` is the pixel count of label `l`.
pub fn components_8(pixels: &[bool], size: ImageSize) -> (Vec<u32>, Vec<usize>) {
    let (w, h) = (size.width, size.height);
    let mut labels = vec![0u32; pixels.len()];
    let mut counts = Vec::new();
    let mut stack = Vec::new();
    for start in 0..pixels.len() {
        if !pixels[start] || labels[start] != 0 {
            continue;
        }
        let label = counts.len() as u32 + 1;
        labels[start] = label;
        stack.push(start);
        let mut count = 0usize;
        while let Some(i) = stack.pop() {
            count += 1;
            let (u, v) = (i % w, i / w);
            for nv in v.saturating_sub(1)..=(v + 1).min(h - 1) {
                for nu in u.saturating_sub(1)..=(u + 1).min(w - 1) {
                    let j = nv * w + nu;
                    if pixels[j] && labels[j] == 0 {
                        labels[j] = label;
                        stack.push(j);
                    }
                }
            }
        }
        counts.push(count);
    }
    (labels, counts)
}

/// `true` for a usable metric depth value: finite and strictly positive (metres).
#[inline]
pub fn is_valid_depth(z: f32) -> bool {
    // = `z.is_finite() && z > 0.0` for every f32 (NaN fails both comparisons), written without
    // a branch so that loops over maps vectorise
    (z > 0.0) & (z < f32::INFINITY)
}

/// A binary region of an image (`true` = inside), e.g. the objects to evaluate or a workspace.
#[derive(Debug, Clone, PartialEq)]
pub struct Mask {
    data: Array2<bool>,
}

impl Mask {
    /// Wraps a `(height, width)` boolean array.
    pub fn new(data: Array2<bool>) -> Self {
        Self { data }
    }
    /// A mask with every pixel inside.
    pub fn full(size: ImageSize) -> Self {
        Self::new(Array2::from_elem(size.shape(), true))
    }
    /// Builds a mask from a row-major buffer of `width * height` values.
    ///
    /// # Errors
    /// [`CoreError::BufferLength`] when the buffer does not match `size`.
    pub fn from_vec(size: ImageSize, data: Vec<bool>) -> Result<Self> {
        let len = data.len();
        Array2::from_shape_vec(size.shape(), data)
            .map(Self::new)
            .map_err(|_| CoreError::BufferLength {
                len,
                size,
                expected: size.pixels(),
            })
    }
    /// The image size.
    pub fn size(&self) -> ImageSize {
        ImageSize::of(&self.data.view())
    }
    /// The `(height, width)` array.
    pub fn data(&self) -> &Array2<bool> {
        &self.data
    }
    /// Number of pixels inside.
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&b| b).count()
    }
    /// Pixel-wise AND of two masks of equal size.
    ///
    /// # Errors
    /// [`CoreError::SizeMismatch`] on different sizes.
    pub fn and(&self, other: &Mask) -> Result<Mask> {
        self.size().expect_eq("mask", other.size())?;
        Ok(Mask::new(
            ndarray::Zip::from(&self.data)
                .and(&other.data)
                .map_collect(|&a, &b| a && b),
        ))
    }

    /// The objects of an image of instance labels, 0 outside (a segmentation's ids, a label
    /// PNG's grey levels or colours), for grasping: touching objects kept apart.
    ///
    /// Inside is every non-zero pixel, except where the image is an **instance label image**:
    /// two or more non-zero values that are objects (a value is an object when at least one of
    /// its pixels has all 8 neighbours of the same value), fewer than [`LABEL_SPECK_SHARE`] of
    /// the non-zero pixels in values that are not (specks), and seams that are few: a pixel
    /// with an 8-neighbour of another non-zero value lies on the seam between two objects, and
    /// the seam pixels must be fewer than [`LABEL_SEAM_SHARE`] of the non-zero pixels. Then the
    /// seam pixels are left out, so that objects that touch never join into one 8-connected
    /// component (one object to grasp). Anything else reads as a binary mask, every non-zero
    /// pixel inside: one value; a mask resized with interpolation (its in-between values run
    /// along edges); a mask saved as JPEG or with a soft gradient (near-equal values in patches,
    /// whose "seams" run everywhere).
    pub fn from_labels(labels: ArrayView2<'_, u64>) -> Mask {
        let (h, w) = labels.dim();
        let mut seen: std::collections::HashMap<u64, (usize, bool)> =
            std::collections::HashMap::new();
        let mut nonzero = 0usize;
        // the seam pixels, cut out where the image is a label image
        let mut seam = Array2::from_elem((h, w), false);
        // whether a neighbour of (v, u) differs from `l` (`nonzero_only`: and is not 0)
        let differs = |v: usize, u: usize, l: u64, nonzero_only: bool| {
            (v.saturating_sub(1)..(v + 2).min(h)).any(|nv| {
                (u.saturating_sub(1)..(u + 2).min(w)).any(|nu| {
                    let n = labels[[nv, nu]];
                    n != l && (!nonzero_only || n != 0)
                })
            })
        };
        for ((v, u), &l) in labels.indexed_iter() {
            if l == 0 {
                continue;
            }
            nonzero += 1;
            seam[[v, u]] = differs(v, u, l, true);
            // interior: all 8 neighbours inside the image and of the same value
            let interior = v > 0 && u > 0 && v + 1 < h && u + 1 < w && !differs(v, u, l, false);
            let e = seen.entry(l).or_insert((0, false));
            e.0 += 1;
            e.1 |= interior;
        }
        let objects = seen.values().filter(|(_, obj)| *obj).count();
        let specks: usize = seen.values().filter(|(_, obj)| !obj).map(|(n, _)| n).sum();
        let share = |k: usize| k as f64 / nonzero.max(1) as f64;
        let seams = seam.iter().filter(|&&b| b).count();
        let is_label_image =
            objects >= 2 && share(specks) < LABEL_SPECK_SHARE && share(seams) < LABEL_SEAM_SHARE;
        Mask::new(
            ndarray::Zip::from(&labels)
                .and(&seam)
                .map_collect(|&l, &on_seam| l != 0 && !(is_label_image && on_seam)),
        )
    }
}

/// [`Mask::from_labels`]: an image of several values is read as instance labels only when
/// fewer than this share of its non-zero pixels lie in values that are no object (specks of a
/// segmentation); more is an interpolated binary mask's edge.
pub const LABEL_SPECK_SHARE: f64 = 0.05;

/// [`Mask::from_labels`]: an image of several values is read as instance labels only when
/// fewer than this share of its non-zero pixels lie on seams between two values (objects that
/// touch share a boundary line; a JPEG's blocks or a gradient of near-equal values have seams
/// everywhere: 18 % and 60 % of a 60 × 80 square in a review's masks).
pub const LABEL_SEAM_SHARE: f64 = 0.1;

/// What a depth model's output means. Kept explicit so that a relative map is never written as
/// metres, nor disparity aligned as depth, by accident.
///
/// Names (files, `--pred-kind`, Python's `kind=`): `metric-depth`, `relative-depth`,
/// `relative-disparity`. Names written by moma before these three existed are read with a fixed
/// mapping ([`PredictionKind::from_name`], docs/formats.md "Prediction kinds"): `inverse-depth`
/// (also `inverse_depth`, `disparity`) is `relative-disparity`; `depth` is `metric-depth` where the
/// writer recorded a metric head or model (the file readers decide that), else `relative-depth`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "&'static str")]
pub enum PredictionKind {
    /// Depth in metres as the model predicts it (a metric head, e.g. Depth Anything V2 metric or
    /// Depth Anything 3 metric): larger = farther, scale nominally known. The only kind that
    /// `raw` (the prediction used as metres) accepts.
    MetricDepth,
    /// Depth up to an unknown scale (and shift): larger = farther, no unit.
    RelativeDepth,
    /// Disparity (inverse depth) up to an unknown scale and shift: larger = nearer, no unit
    /// (Depth Anything's relative models).
    RelativeDisparity,
}

impl PredictionKind {
    /// Every kind, in documentation order.
    pub const ALL: [PredictionKind; 3] = [
        PredictionKind::MetricDepth,
        PredictionKind::RelativeDepth,
        PredictionKind::RelativeDisparity,
    ];

    /// The file and command-line name: `metric-depth`, `relative-depth` or `relative-disparity`.
    pub const fn name(self) -> &'static str {
        match self {
            Self::MetricDepth => "metric-depth",
            Self::RelativeDepth => "relative-depth",
            Self::RelativeDisparity => "relative-disparity",
        }
    }

    /// `true` for disparity (larger = nearer), `false` for the two depth kinds.
    pub const fn is_disparity(self) -> bool {
        matches!(self, Self::RelativeDisparity)
    }

    /// `true` for `metric-depth` only: values nominally in metres.
    pub const fn is_metric(self) -> bool {
        matches!(self, Self::MetricDepth)
    }

    /// Whether a calibration fitted on predictions of kind `self` may align a prediction of kind
    /// `pred`: the same kind, or metric depth under a `relative-depth` calibration (a metric map
    /// is a depth map whose scale happens to be known, and a relative-depth fit estimates the
    /// scale anyway). The converse is refused: a `metric-depth` calibration may use the values
    /// as metres (`raw`), which a relative map is not. This also keeps a calibration file written
    /// before the three kinds existed (kind `depth`, read as `relative-depth` unless its method
    /// is `raw`) usable on a metric model's predictions.
    pub const fn accepts(self, pred: PredictionKind) -> bool {
        matches!(
            (self, pred),
            (Self::MetricDepth, Self::MetricDepth)
                | (Self::RelativeDepth, Self::RelativeDepth | Self::MetricDepth)
                | (Self::RelativeDisparity, Self::RelativeDisparity)
        )
    }

    /// The kind called `name`: one of the three names, or a name written before they existed:
    /// `inverse-depth`, `inverse_depth` and `disparity` are `relative-disparity`, and `depth` is
    /// `legacy_depth`, which the caller decides from what the writer recorded (`metric-depth`
    /// for a metric head or model, else `relative-depth`; [`str::parse`] uses
    /// `relative-depth`, the kind that claims no unit).
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] for any other name, listing the three names.
    pub fn from_name(name: &str, legacy_depth: PredictionKind) -> Result<Self> {
        match name {
            "inverse-depth" | "inverse_depth" | "disparity" => Ok(Self::RelativeDisparity),
            "depth" => Ok(legacy_depth),
            other => crate::names::parse(other, &Self::ALL, Self::name, "prediction kind"),
        }
    }
}

impl std::fmt::Display for PredictionKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for PredictionKind {
    type Err = CoreError;
    /// [`PredictionKind::from_name`] with an old `depth` read as `relative-depth`.
    fn from_str(s: &str) -> Result<Self> {
        Self::from_name(s, Self::RelativeDepth)
    }
}

impl TryFrom<String> for PredictionKind {
    type Error = CoreError;
    fn try_from(s: String) -> Result<Self> {
        s.parse()
    }
}

impl From<PredictionKind> for &'static str {
    fn from(k: PredictionKind) -> Self {
        k.name()
    }
}

/// A depth model's raw output: unitless (or metres for a metric head, but not yet trusted as such).
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// `(height, width)` values as the model produced them.
    pub values: Array2<f32>,
    /// What the values mean.
    pub kind: PredictionKind,
}

impl Prediction {
    /// Wraps a map with its kind.
    pub fn new(values: Array2<f32>, kind: PredictionKind) -> Self {
        Self { values, kind }
    }
    /// The image size.
    pub fn size(&self) -> ImageSize {
        ImageSize::of(&self.values.view())
    }
}

/// Metric depth in metres along the optical axis; invalid pixels are `NaN` (or `0` when read from a sensor).
#[derive(Debug, Clone, PartialEq)]
pub struct MetricDepth {
    /// `(height, width)` depth in metres.
    pub depth_m: Array2<f32>,
}

impl MetricDepth {
    /// Wraps a `(height, width)` map of metres.
    pub fn new(depth_m: Array2<f32>) -> Self {
        Self { depth_m }
    }
    /// The image size.
    pub fn size(&self) -> ImageSize {
        ImageSize::of(&self.depth_m.view())
    }
    /// Mask of pixels holding a valid depth ([`is_valid_depth`]).
    pub fn valid_mask(&self) -> Mask {
        Mask::new(self.depth_m.mapv(is_valid_depth))
    }
    /// Number of valid pixels.
    pub fn valid_count(&self) -> usize {
        // over the memory as one slice when it is one (every map moma makes): ndarray's 2-D
        // iterator does not vectorise
        match self.depth_m.as_slice_memory_order() {
            Some(zs) => zs.iter().map(|&z| usize::from(is_valid_depth(z))).sum(),
            None => self.depth_m.iter().filter(|&&z| is_valid_depth(z)).count(),
        }
    }
}

/// Depth in metres beyond which a map's median says it holds millimetres (a raw RealSense-style
/// PNG cast to float without dividing by 1000). No depth model or sensor moma serves sees a
/// median of 200 m.
pub const MILLIMETRE_MEDIAN_M: f32 = 200.0;

/// Depth in metres below which a map's median says it is not metres: a uint16 millimetre PNG
/// written from metres (values 0–5 for a scene 0–5 m away), or metres divided by 1000 twice.
/// No sensor or depth model moma serves sees a median of 2 cm (a RealSense D405 starts at 7 cm).
pub const NEAR_MEDIAN_M: f32 = 0.02;

/// What a depth map's median says of its units when they cannot be metres ([`unit_mistake`]);
/// each holds the median, metres as read.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum UnitMistake {
    /// Above [`MILLIMETRE_MEDIAN_M`]: millimetres given as metres.
    Millimetres(f32),
    /// Below [`NEAR_MEDIAN_M`]: metres written as millimetres, or divided by 1000 once too
    /// often (or no depth map at all).
    TooNear(f32),
}

/// The units a depth map read as metres cannot have, from the median of its valid pixels
/// ([`is_valid_depth`]): above [`MILLIMETRE_MEDIAN_M`] or below [`NEAR_MEDIAN_M`]. `None` for a
/// plausible map or one without valid pixels. The one rule for every reader of metres (the
/// CLI's depth files, Python's arrays, the ROS 2 node's depth sensor).
pub fn unit_mistake(depth_m: ndarray::ArrayView2<'_, f32>) -> Option<UnitMistake> {
    // The median (sorted[n / 2] of the n valid depths) is above a bound exactly when at least
    // n − n / 2 of them are, and below one exactly when at least n / 2 + 1 are: one pass that
    // allocates nothing decides the usual case (the check runs on every frame RAW aligns), and
    // only a map whose median is beyond a bound is sorted for the value its message names.
    let (mut n, mut above, mut below) = (0usize, 0usize, 0usize);
    for &z in &depth_m {
        if is_valid_depth(z) {
            n += 1;
            above += usize::from(z > MILLIMETRE_MEDIAN_M);
            below += usize::from(z < NEAR_MEDIAN_M);
        }
    }
    let mistake: fn(f32) -> UnitMistake = if n > 0 && above >= n - n / 2 {
        UnitMistake::Millimetres
    } else if n > 0 && below > n / 2 {
        UnitMistake::TooNear
    } else {
        return None;
    };
    valid_median_m(depth_m).map(mistake)
}

/// The (upper) median of a depth map's valid pixels ([`is_valid_depth`]), `sorted[n / 2]`;
/// `None` without one.
pub fn valid_median_m(depth_m: ndarray::ArrayView2<'_, f32>) -> Option<f32> {
    let mut valid: Vec<f32> = depth_m
        .iter()
        .copied()
        .filter(|&z| is_valid_depth(z))
        .collect();
    median_in_place(&mut valid)
}

/// The (upper) median of `xs`, reordering them; `None` when empty.
pub(crate) fn median_in_place(xs: &mut [f32]) -> Option<f32> {
    if xs.is_empty() {
        return None;
    }
    let k = xs.len() / 2;
    let (_, m, _) = xs.select_nth_unstable_by(k, f32::total_cmp);
    Some(*m)
}

/// The median of a depth map's valid pixels when it is above [`MILLIMETRE_MEDIAN_M`]: the map
/// can only be millimetres given as metres ([`unit_mistake`]).
pub fn millimetre_median(depth_m: ndarray::ArrayView2<'_, f32>) -> Option<f32> {
    match unit_mistake(depth_m) {
        Some(UnitMistake::Millimetres(median)) => Some(median),
        _ => None,
    }
}

#[cfg(test)]
mod millimetre_median_tests {
    use super::*;

    /// The median rule written out: `sorted[n / 2]` of the valid depths of `v` when `beyond`
    /// holds for it.
    fn median_rule(v: &[f32], beyond: impl Fn(f32) -> bool) -> Option<f32> {
        let mut valid: Vec<f32> = v.iter().copied().filter(|&z| is_valid_depth(z)).collect();
        if valid.is_empty() {
            return None;
        }
        valid.sort_by(f32::total_cmp);
        let m = valid[valid.len() / 2];
        beyond(m).then_some(m)
    }

    /// `check` against [`median_rule`] on maps of both parities with every share of values
    /// beyond the bound (`outside(i)`) around one half, values equal to the bound, and invalid
    /// pixels; and on a map without a valid pixel.
    fn decides_as_the_median_does(
        check: fn(ndarray::ArrayView2<'_, f32>) -> Option<f32>,
        beyond: impl Fn(f32) -> bool + Copy,
        outside: impl Fn(usize) -> f32,
        bound: f32,
    ) {
        for n in 1..=9usize {
            for k in 0..=n {
                for tie in [false, true] {
                    let mut v: Vec<f32> = (0..n)
                        .map(|i| {
                            if i < k {
                                outside(i)
                            } else if tie {
                                bound
                            } else {
                                0.7 + i as f32 * 0.01
                            }
                        })
                        .collect();
                    v.extend([f32::NAN, 0.0, -1.0, f32::INFINITY]);
                    let map = ndarray::Array2::from_shape_vec((1, v.len()), v.clone()).unwrap();
                    assert_eq!(check(map.view()), median_rule(&v, beyond), "{v:?}");
                }
            }
        }
        let none = ndarray::Array2::from_elem((2, 2), f32::NAN);
        assert_eq!(check(none.view()), None);
    }

    /// The counting shortcut gives exactly the median rule it stands for, above the bound
    /// (millimetres given as metres).
    #[test]
    fn the_count_decides_as_the_median_does() {
        decides_as_the_median_does(
            millimetre_median,
            |m| m > MILLIMETRE_MEDIAN_M,
            |i| 650.0 + i as f32,
            MILLIMETRE_MEDIAN_M,
        );
    }

    /// The same below [`NEAR_MEDIAN_M`] (metres written into a millimetre PNG: 1–9 mm).
    #[test]
    fn the_count_decides_as_the_median_does_below() {
        decides_as_the_median_does(
            |d| match unit_mistake(d) {
                Some(UnitMistake::TooNear(median)) => Some(median),
                _ => None,
            },
            |m| m < NEAR_MEDIAN_M,
            |i| 0.001 * (1 + i) as f32,
            NEAR_MEDIAN_M,
        );
    }
}

#[cfg(test)]
mod valid_depth_tests {
    use super::is_valid_depth;

    /// The branch-free form equals `is_finite() && > 0` on every special value and around them.
    #[test]
    fn valid_depth_is_finite_and_positive() {
        for z in [
            0.0f32,
            -0.0,
            f32::MIN_POSITIVE,
            1e-45,
            -1e-45,
            1.0,
            -1.0,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
        ] {
            assert_eq!(is_valid_depth(z), z.is_finite() && z > 0.0, "{z}");
        }
    }
}

#[cfg(test)]
mod label_tests {
    use super::{ImageSize, Mask, components_8};
    use ndarray::Array2;

    fn components(m: &Mask) -> Vec<usize> {
        let flat: Vec<bool> = m.data().iter().copied().collect();
        components_8(&flat, m.size()).1
    }

    /// Two 20 × 20 squares side by side (columns 10–29 and 30–49, rows 10–29) with values `a`
    /// and `b`, on a 60 × 40 image.
    fn touching(a: u64, b: u64) -> Array2<u64> {
        Array2::from_shape_fn((40, 60), |(v, u)| match (v, u) {
            (10..30, 10..30) => a,
            (10..30, 30..50) => b,
            _ => 0,
        })
    }

    #[test]
    fn touching_instances_are_kept_apart_by_their_seam() {
        let m = Mask::from_labels(touching(100, 200).view());
        // one component per instance, each losing only its column along the seam
        assert_eq!(components(&m), [19 * 20, 19 * 20]);
        for v in 10..30 {
            assert!(!m.data()[[v, 29]] && !m.data()[[v, 30]]);
            assert!(m.data()[[v, 28]] && m.data()[[v, 31]]);
        }
        // the same image as one value (a binary mask) is one object, every pixel inside
        let binary = Mask::from_labels(touching(255, 255).view());
        assert_eq!(components(&binary), [800]);
        // instances that do not touch lose nothing
        let apart = Array2::from_shape_fn((40, 60), |(v, u)| match (v, u) {
            (10..30, 5..25) => 7u64,
            (10..30, 35..55) => 9,
            _ => 0,
        });
        assert_eq!(components(&Mask::from_labels(apart.view())), [400, 400]);
        let size = ImageSize::new(60, 40);
        assert_eq!(
            Mask::from_labels(Array2::zeros((40, 60)).view()),
            Mask::new(Array2::from_elem(size.shape(), false))
        );
    }

    #[test]
    fn an_interpolated_binary_mask_is_not_taken_for_labels() {
        // a 255 square whose edge ramps 64, 128, 192 outwards over three one-pixel rings (a
        // mask resized with interpolation): the in-between values are no objects
        let m = Array2::from_shape_fn((40, 40), |(v, u)| {
            let d = (v as i64 - 20).abs().max((u as i64 - 20).abs());
            match d {
                0..=8 => 255u64,
                9 => 192,
                10 => 128,
                11 => 64,
                _ => 0,
            }
        });
        let mask = Mask::from_labels(m.view());
        assert_eq!(mask.count(), 23 * 23, "every non-zero pixel inside");
        // a 64 × 80 square of flat 8 × 8 blocks of 254 and 255 (a mask saved as JPEG), and one
        // of a soft gradient 230 → 255 in 3-pixel bands: both have values that are objects, but
        // seams everywhere; each reads whole
        for square in [
            Array2::from_shape_fn((72, 88), |(v, u)| match (v, u) {
                (4..68, 4..84) => 254 + ((v / 8 + u / 8) % 2) as u64,
                _ => 0,
            }),
            Array2::from_shape_fn((72, 88), |(v, u)| match (v, u) {
                (4..68, 4..84) => 230 + (u as u64 - 4) / 3,
                _ => 0,
            }),
        ] {
            assert_eq!(Mask::from_labels(square.view()).count(), 64 * 80);
        }
        // a segmentation's speck (one pixel of a third value) does not stop two instances
        let mut labels = touching(1, 2);
        labels[[2, 2]] = 3;
        assert_eq!(components(&Mask::from_labels(labels.view())), [1, 380, 380]);
    }
}

#[cfg(test)]
mod tests {
    use super::PredictionKind::{self, *};

    #[test]
    fn kind_names_round_trip_and_old_names_map() {
        for k in PredictionKind::ALL {
            assert_eq!(k.name().parse::<PredictionKind>().unwrap(), k);
            let json = serde_json::to_string(&k).unwrap();
            assert_eq!(json, format!("\"{}\"", k.name()));
            assert_eq!(serde_json::from_str::<PredictionKind>(&json).unwrap(), k);
        }
        for old in ["inverse-depth", "inverse_depth", "disparity"] {
            assert_eq!(old.parse::<PredictionKind>().unwrap(), RelativeDisparity);
        }
        assert_eq!("depth".parse::<PredictionKind>().unwrap(), RelativeDepth);
        assert_eq!(
            PredictionKind::from_name("depth", MetricDepth).unwrap(),
            MetricDepth
        );
        let e = "metres".parse::<PredictionKind>().unwrap_err().to_string();
        assert!(
            e.contains("'metres'")
                && e.contains("metric-depth, relative-depth, relative-disparity"),
            "{e}"
        );
        assert!(serde_json::from_str::<PredictionKind>("\"metres\"").is_err());
    }

    /// Metric depth may go where relative depth is expected, never the reverse, and disparity
    /// only with disparity.
    #[test]
    fn a_calibration_accepts_its_kind_and_metric_under_relative_depth() {
        let accepted: Vec<(PredictionKind, PredictionKind)> = PredictionKind::ALL
            .into_iter()
            .flat_map(|c| PredictionKind::ALL.map(|p| (c, p)))
            .filter(|&(c, p)| c.accepts(p))
            .collect();
        assert_eq!(
            accepted,
            [
                (MetricDepth, MetricDepth),
                (RelativeDepth, MetricDepth),
                (RelativeDepth, RelativeDepth),
                (RelativeDisparity, RelativeDisparity)
            ]
        );
    }
}
