//! Per-frame re-alignment on static anchors (docs/method.md §10).
//!
//! In a fixed-camera cell the calibration frame's ground truth stays valid wherever the scene
//! has not changed (table, bin walls). The calibration keeps a compact [`AnchorStore`] — the
//! calibration RGB reduced to grey at half resolution (u8), its ground-truth depth at the same
//! half-resolution pixels (u16 millimetres), the calibration's own one-shot result there (u16 mm)
//! and the calibration's normalised prediction there (f32) — and every new RGB frame yields free
//! metric anchors: pixels whose appearance is unchanged since calibration.
//!
//! # The anchor rule ([`AnchorThresholds`])
//! Grey g = (R + 2G + B)/4, averaged over 2×2 blocks (half resolution, which also halves sensor
//! noise): a [`GreyHalf`], which `moma_io::grey_half` makes from an RGB image (the conversion
//! lives with the images; the rule below works on greys). For the frame (g_f) against the
//! calibration (g_c):
//! 1. **Global gain** k = median of g_f/g_c over pixels with g_c in [20, 235] and g_f in
//!    [1, 250] (every 7th half-resolution pixel): absorbs a global brightness / exposure change;
//!    new objects are a minority and do not move the median. A gain outside
//!    [[`MIN_GAIN`], [`MAX_GAIN`]] = [0.25, 4] (lens covered, lights off) gives no anchors: it
//!    would squeeze the calibration's texture below the grey tolerance, so that a uniform frame
//!    matched everywhere.
//! 2. **Pixel match under a displacement** s (one of the 9 half-resolution shifts of a 3×3 set):
//!    g_f(p) ≤ 250 (not saturated) and |g_f(p) − k·g_c(p + s)| ≤ `abs_grey` + `rel`·k·g_c(p)
//!    (defaults 6 grey levels and 8 %; the relative term absorbs noise that grows with
//!    brightness).
//! 3. **Patch match**: p is unchanged if for some displacement s *every* pixel of its 3×3
//!    half-resolution patch matches under that same s. The common displacement tolerates one to
//!    two full-resolution pixels of vibration without letting a textured new object pass by
//!    matching each pixel to a different neighbour; object borders drop out.
//!    Rules 2–3 are tested at candidate pixels only, every [`ANCHOR_STRIDE`]-th
//!    half-resolution pixel in each direction (4 800 candidates at 640×480), the undisplaced
//!    patch first.
//! 4. **Valid static depth**: the stored calibration depth at the pixel is valid and within 3 %
//!    of its 3×3 half-resolution neighbours (no depth edge, where vibration or the model's edge
//!    smoothing would make the anchor wrong).
//!
//! Shadows lower the brightness locally by more than the tolerance and so remove anchors rather
//! than add wrong ones (conservative). A new object of exactly the background's grey and no
//! texture would pass the test: the residual trimming and the held-out check below guard against
//! such anchors.
//!
//! # The corrections ([`RealignConfig`], [`CorrectionModel`])
//! **`prediction-affine`** works on the frame's *normalised prediction* ẑ (the map the
//! calibration's model is applied to). Per-frame min-max statistics (new objects change the
//! map's minimum and maximum) and a depth model's per-frame scale and shift in its own output
//! space both change the prediction of the unchanged background by an affine map, for every
//! method. With ẑ_c the calibration frame's normalised prediction stored at the anchor, ẑ the
//! frame's, m and σ the mean and standard deviation of ẑ over the fitting anchors and R the range
//! of the stored ẑ_c (the unit of the correction), the corrected map is
//! ẑ' = ẑ + R·(c₀·(ẑ − m)/σ + c₁), c minimising Σ((ẑ_c − ẑ)/R − c₀·(ẑ − m)/σ − c₁)² + λ‖c‖²
//! (centred and standardised: slope and shift are not collinear and each feature has Σf² = n,
//! so λ counts anchor equivalents for both, as for the other forms). The
//! calibration's model is applied to ẑ' = a·ẑ + b: exact for that change whatever the method
//! (SSRA, LWLR and the local variants included), and it leaves the calibration's fit as it was
//! (target `calibration-output` only). Held-out errors are measured in metres through the
//! model: |model(ẑ') − model(ẑ_c)| at each held-out anchor (`AlignmentModel::predict_at`).
//!
//! **`scale-shift`** and **`planar`** correct the one-shot metres instead. In the calibration's
//! alignment space (target t = z in depth space, 1/z in inverse space), with
//! y the one-shot result's target at an anchor, y₀ the mean of y over the fitting anchors and
//! s = y/y₀, the corrected target is t̂ = y + y₀·c·f with
//! f = [s, 1] (`scale-shift`: a relative scale change and a shift, the form of the per-frame
//! fluctuation a/z + b of a depth model) or f = [s, 1, s·(u/W − ½), s·(v/H − ½)] (`planar`:
//! a planar scale field, SSRA's form, and a shift). Ridge towards the identity (c = 0):
//! minimise Σ((t − y)/y₀ − c·f)² + λ‖c‖², λ = `ridge` (dimensionless, in "anchor
//! equivalents": well-determined directions, Σf² ≈ number of anchors, are barely shrunk; on a
//! flat background scale and shift are nearly collinear and the ridge splits the correction
//! between them instead of extrapolating an ill-determined scale to nearer objects).
//! One trimming pass drops anchors whose residual is beyond 3 robust standard deviations
//! (1.4826·MAD) and refits (every form). Up to `max_anchors` anchors are used (a seeded
//! subsample); a seeded split holds out `holdout_fraction` of them.
//!
//! # Acceptance
//! The correction is **accepted only if it lowers the error on the held-out anchors by more
//! than `acceptance_se` standard errors** (default 1): with e_b, e_a the absolute held-out errors
//! (metres) before and after the correction, the paired gains d = e_b − e_a of the held-out
//! anchors without the [`HELD_OUT_TRIM`] fraction with the largest error before or after (false
//! anchors), accepted iff mean(d) > 0 and mean(d) > `acceptance_se`·sd(d)/√n. A correction that
//! only fits noise gains nothing on average on held-out anchors and then passes one standard
//! error about one time in six, not one time in two. Accepted corrections are refitted on all
//! used anchors. Otherwise, and when fewer than max(`min_anchors`, `min_anchor_fraction` × the
//! store's candidates) anchors remain, the one-shot result is kept and the [`RealignReport`]
//! says why (with the trimmed held-out RMSE before/after, the mean gain and its standard error).
//! The report never holds NaN.
//!
//! # What it cannot correct
//! Re-alignment on the calibration's own output restores the calibration frame's state; the
//! calibration's own error on objects (a depth model flattening objects towards the table,
//! seeing through glass) stays. Where a frame's change happened to offset that error, removing
//! the change makes that frame worse on its objects while its background improves (measured on
//! SIMULATED predictions in docs/evaluation.md, example `realign_diag`).
//!
//! Store size at 640×480: 320×240 half-resolution pixels × (1 byte grey + 2 bytes depth + 2 bytes
//! one-shot + 4 bytes normalised prediction) = 691 200 bytes, 921 600 characters of base64 in the
//! calibration file (230 400 bytes for a store of grey and depth only; the file form, base64 of
//! the little-endian arrays, is moma-io's). Stores written without the normalised prediction
//! read unchanged and serve `scale-shift` and `planar`.

use ndarray::{Array2, ArrayView2, ArrayViewMut2};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::align::AlignmentModel;
use crate::error::{CoreError, Result};
use crate::image::{ImageSize, MetricDepth, is_valid_depth, median_in_place};
use crate::normalise::AlignSpace;

/// Anchor candidates are every `ANCHOR_STRIDE`-th half-resolution pixel in each direction (a
/// full-resolution stride of 4 pixels): 4 800 candidates at 640×480, far more than a correction
/// of at most four parameters needs, at a quarter of the cost.
pub const ANCHOR_STRIDE: usize = 2;

/// Plausible range of the global brightness gain k (rule 1): outside it the frame has no
/// anchors (a gain of 1/4 or less squeezes the calibration's texture below the grey tolerance).
pub const MIN_GAIN: f32 = 0.25;
/// Upper end of the plausible gain range (see [`MIN_GAIN`]).
pub const MAX_GAIN: f32 = 4.0;

/// Smallest image an anchor store accepts, pixels per side.
pub const MIN_ANCHOR_IMAGE_SIDE_PX: usize = 8;

/// The compact calibration-frame record re-alignment needs: grey (u8) and ground-truth depth
/// (u16 mm, 0 = invalid or on a depth edge) at half resolution, and optionally the calibration's
/// own one-shot result (u16 mm) and normalised prediction (f32) at the same pixels.
///
/// Half-resolution pixel (i, j) covers full-resolution rows 2i, 2i+1 and columns 2j, 2j+1; its
/// grey is the block mean, its depth the ground truth at full-resolution pixel (u = 2j, v = 2i).
/// This crate holds no file form: the calibration file (`moma_io`) stores it as
/// `calibration.anchors`, through [`AnchorStore::from_parts`] and the accessors.
#[derive(Debug, Clone, PartialEq)]
pub struct AnchorStore {
    size: ImageSize,
    grey: Array2<u8>,
    depth_mm: Array2<u16>,
    one_shot_mm: Option<Array2<u16>>,
    normalised: Option<Array2<f32>>,
}

fn half(size: ImageSize) -> (usize, usize) {
    (size.height / 2, size.width / 2)
}

/// A frame as the anchor rule compares it: grey g = (R + 2G + B)/4 averaged over 2×2 blocks,
/// f32 in [0, 255], at half resolution `(height/2, width/2)` of a full-resolution image of
/// [`GreyHalf::size`] (module documentation, "The anchor rule"; its grey tolerances are in these
/// levels). The conversion from RGB lives with the images: `moma_io::grey_half`.
#[derive(Debug, Clone, PartialEq)]
pub struct GreyHalf {
    size: ImageSize,
    values: Array2<f32>,
}

impl GreyHalf {
    /// Wraps the half-resolution grey `values` of an image of full-resolution `size`.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`]: `values` not `(height/2, width/2)` in standard layout,
    /// or a value outside [0, 255] (NaN included).
    pub fn new(size: ImageSize, values: Array2<f32>) -> Result<Self> {
        let (hh, hw) = half(size);
        if values.dim() != (hh, hw) || !values.is_standard_layout() {
            return Err(CoreError::InvalidParameter(format!(
                "half-resolution grey of a {size} image must be {hw}x{hh} (row-major), got {}x{}",
                values.ncols(),
                values.nrows()
            )));
        }
        if let Some(g) = values.iter().find(|g| !(0.0..=255.0).contains(*g)) {
            return Err(CoreError::InvalidParameter(format!(
                "grey level {g} is outside [0, 255]"
            )));
        }
        Ok(Self { size, values })
    }

    /// Full-resolution image size, pixels.
    pub fn size(&self) -> ImageSize {
        self.size
    }

    /// The grey levels, `(height/2, width/2)`.
    pub fn values(&self) -> ArrayView2<'_, f32> {
        self.values.view()
    }

    /// Row-major grey levels (standard layout is checked at construction).
    fn as_slice(&self) -> &[f32] {
        self.values.as_slice().unwrap_or(&[])
    }
}

impl AnchorStore {
    /// Builds the store from the calibration frame's grey ([`GreyHalf`], from its RGB) and
    /// ground truth.
    ///
    /// # Errors
    /// Size mismatch between `grey` and `gt`, an image smaller than 8×8, no pixel with valid
    /// static depth.
    pub fn new(grey: &GreyHalf, gt: &MetricDepth) -> Result<Self> {
        let size = gt.size();
        size.expect_eq("calibration RGB", grey.size())?;
        if size.width < MIN_ANCHOR_IMAGE_SIDE_PX || size.height < MIN_ANCHOR_IMAGE_SIDE_PX {
            return Err(CoreError::InvalidParameter(format!(
                "anchor store needs an image of at least {MIN_ANCHOR_IMAGE_SIDE_PX}x{MIN_ANCHOR_IMAGE_SIDE_PX} pixels, got {size}"
            )));
        }
        let (hh, hw) = half(size);
        let grey = grey.values.mapv(|x| x.round() as u8);
        let z = Array2::from_shape_fn((hh, hw), |(i, j)| {
            let z = gt.depth_m[[2 * i, 2 * j]];
            if is_valid_depth(z) && z * 1000.0 < u16::MAX as f32 - 0.5 {
                z
            } else {
                f32::NAN
            }
        });
        // valid only away from depth edges: every 3×3 neighbour valid and within 3 % of the
        // centre ([`crate::sampling::EDGE_JUMP_REL`], the constant of the calibration samples'
        // edge margin; here on 3×3 half-resolution neighbours)
        let depth_mm = Array2::from_shape_fn((hh, hw), |(i, j)| {
            let c = z[[i, j]];
            if !c.is_finite() {
                return 0u16;
            }
            for di in [-1isize, 0, 1] {
                for dj in [-1isize, 0, 1] {
                    let (a, b) = (i as isize + di, j as isize + dj);
                    if a < 0 || b < 0 || a >= hh as isize || b >= hw as isize {
                        continue;
                    }
                    let n = z[[a as usize, b as usize]];
                    if !n.is_finite() || (n - c).abs() > crate::sampling::EDGE_JUMP_REL * c {
                        return 0;
                    }
                }
            }
            (c * 1000.0).round().max(1.0) as u16
        });
        let store = Self {
            size,
            grey,
            depth_mm,
            one_shot_mm: None,
            normalised: None,
        };
        if store.valid_depth_px() == 0 {
            return Err(CoreError::NoValidPixels(
                "the calibration ground truth holds no valid depth away from depth edges for the anchor store".into(),
            ));
        }
        Ok(store)
    }

    /// Records the calibration's one-shot result on the calibration frame (metres, full
    /// resolution) at the store's pixels, for the `calibration-output` target.
    ///
    /// # Errors
    /// Size mismatch.
    pub fn with_one_shot(mut self, one_shot: &MetricDepth) -> Result<Self> {
        self.size
            .expect_eq("calibration one-shot depth", one_shot.size())?;
        let (hh, hw) = half(self.size);
        self.one_shot_mm = Some(Array2::from_shape_fn((hh, hw), |(i, j)| {
            let z = one_shot.depth_m[[2 * i, 2 * j]];
            if is_valid_depth(z) && z * 1000.0 < u16::MAX as f32 - 0.5 {
                (z * 1000.0).round().max(1.0) as u16
            } else {
                0
            }
        }));
        Ok(self)
    }

    /// Records the calibration's normalised prediction ẑ of the calibration frame (full
    /// resolution, the map the calibration was fitted on) at the store's pixels, for the
    /// `prediction-affine` correction.
    ///
    /// # Errors
    /// Size mismatch.
    pub fn with_normalised(mut self, normalised: ArrayView2<'_, f32>) -> Result<Self> {
        self.size.expect_eq(
            "calibration normalised prediction",
            ImageSize::of(&normalised),
        )?;
        let (hh, hw) = half(self.size);
        self.normalised = Some(Array2::from_shape_fn((hh, hw), |(i, j)| {
            let x = normalised[[2 * i, 2 * j]];
            if x.is_finite() { x } else { f32::NAN }
        }));
        Ok(self)
    }

    /// Whether the calibration's normalised prediction is stored (needed by
    /// [`CorrectionModel::PredictionAffine`]).
    pub fn has_normalised(&self) -> bool {
        self.normalised.is_some()
    }

    /// Whether the calibration's one-shot result is stored.
    pub fn has_one_shot(&self) -> bool {
        self.one_shot_mm.is_some()
    }

    /// Full-resolution image size, pixels.
    pub fn image_size(&self) -> ImageSize {
        self.size
    }

    /// Half-resolution pixels holding a valid static depth.
    pub fn valid_depth_px(&self) -> usize {
        self.depth_mm.iter().filter(|&&d| d > 0).count()
    }

    /// The share of the calibration frame's (half-resolution) grey that is saturated, above
    /// [`SATURATED_GREY`]: no anchor can lie there (rule 2).
    pub fn saturated_share(&self) -> f64 {
        saturated_share(self.grey.iter().map(|&c| f32::from(c)), self.grey.len())
    }

    /// The warning for a mostly saturated calibration RGB (a share of at least
    /// [`SATURATED_WARN_SHARE`] above [`SATURATED_GREY`]), `None` otherwise: no anchor can lie
    /// there, and later frames keep the one-shot depth where too few are left. One text for
    /// `moma calibrate --anchors` and Python's `calibrate(anchors_rgb=)`.
    pub fn saturation_warning(&self) -> Option<String> {
        let share = self.saturated_share();
        (share >= SATURATED_WARN_SHARE).then(|| {
            format!(
                "{:.0} % of the calibration frame's RGB is saturated (grey above \
                 {SATURATED_GREY}): no anchor can lie there, and re-alignment will keep the \
                 one-shot depth where too few are left; lower the camera's exposure or gain and \
                 calibrate again",
                share * 100.0
            )
        })
    }

    /// Anchor candidates (every [`ANCHOR_STRIDE`]-th interior half-resolution pixel in each
    /// direction) holding a valid static depth: the most anchors a frame can have.
    pub fn candidate_px(&self) -> usize {
        let (hh, hw) = half(self.size);
        (1..hh.saturating_sub(1))
            .step_by(ANCHOR_STRIDE)
            .map(|i| {
                (1..hw.saturating_sub(1))
                    .step_by(ANCHOR_STRIDE)
                    .filter(|&j| self.depth_mm[[i, j]] > 0)
                    .count()
            })
            .sum()
    }

    /// Size of the stored arrays, bytes (before base64).
    pub fn stored_bytes(&self) -> usize {
        self.grey.len()
            + 2 * self.depth_mm.len()
            + self.one_shot_mm.as_ref().map_or(0, |a| 2 * a.len())
            + self.normalised.as_ref().map_or(0, |a| 4 * a.len())
    }

    /// A store from its arrays, as a file reader decodes them: `size` the full-resolution
    /// image size, every array `(height/2, width/2)`; `normalised` NaN where none.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`]: a size below 8×8 or above the image limit, an array of
    /// another shape, an infinite normalised value.
    pub fn from_parts(
        size: ImageSize,
        grey: Array2<u8>,
        depth_mm: Array2<u16>,
        one_shot_mm: Option<Array2<u16>>,
        normalised: Option<Array2<f32>>,
    ) -> Result<Self> {
        let store = Self {
            size,
            grey,
            depth_mm,
            one_shot_mm,
            normalised,
        };
        store.validate()?;
        if store
            .normalised
            .as_ref()
            .is_some_and(|a| a.iter().any(|x| x.is_infinite()))
        {
            return Err(CoreError::InvalidParameter(
                "anchor store normalised prediction holds an infinite value".into(),
            ));
        }
        Ok(store)
    }

    /// Grey at half resolution, `(height/2, width/2)`.
    pub fn grey(&self) -> ArrayView2<'_, u8> {
        self.grey.view()
    }

    /// Ground-truth depth at half resolution, millimetres (0 = invalid or on a depth edge).
    pub fn depth_mm(&self) -> ArrayView2<'_, u16> {
        self.depth_mm.view()
    }

    /// The calibration's one-shot result at the same pixels, millimetres (0 = none), if stored.
    pub fn one_shot_mm(&self) -> Option<ArrayView2<'_, u16>> {
        self.one_shot_mm.as_ref().map(|a| a.view())
    }

    /// The calibration's normalised prediction at the same pixels (NaN = none), if stored.
    pub fn normalised(&self) -> Option<ArrayView2<'_, f32>> {
        self.normalised.as_ref().map(|a| a.view())
    }

    /// Checks internal consistency (array shapes against the image size).
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the problem.
    pub fn validate(&self) -> Result<()> {
        let (hh, hw) = half(self.size);
        if self.size.width < MIN_ANCHOR_IMAGE_SIDE_PX
            || self.size.height < MIN_ANCHOR_IMAGE_SIDE_PX
            || !self.size.is_within_limits()
        {
            return Err(CoreError::InvalidParameter(format!(
                "anchor store image size {} is too small or too large",
                self.size
            )));
        }
        if self.grey.dim() != (hh, hw)
            || self.depth_mm.dim() != (hh, hw)
            || self
                .one_shot_mm
                .as_ref()
                .is_some_and(|a| a.dim() != (hh, hw))
            || self
                .normalised
                .as_ref()
                .is_some_and(|a| a.dim() != (hh, hw))
        {
            return Err(CoreError::InvalidParameter(format!(
                "anchor store arrays are not {hw}x{hh} (half of {})",
                self.size
            )));
        }
        Ok(())
    }
}

/// Thresholds of the anchor rule (module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AnchorThresholds {
    /// Absolute grey tolerance, grey levels (0–255) after the gain (default 6).
    pub abs_grey: f32,
    /// Relative grey tolerance, fraction of the gain-corrected calibration grey (default 0.08).
    pub rel: f32,
}

impl Default for AnchorThresholds {
    fn default() -> Self {
        Self {
            abs_grey: 6.0,
            rel: 0.08,
        }
    }
}

/// Form of the correction fitted on the anchors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum CorrectionModel {
    /// δ = c₀ + c₁·y': scale and shift of the one-shot result in the alignment space.
    #[default]
    ScaleShift,
    /// δ = c₀ + c₁·y' + c₂·u' + c₃·v': plus a planar shift over the image.
    Planar,
    /// An affine map ẑ' = a·ẑ + b of the frame's *normalised prediction*, fitted at the anchors
    /// to reproduce the calibration frame's normalised prediction there, then the calibration's
    /// model applied: exact for every method when the background's prediction changed by an
    /// affine map (per-frame min-max statistics, a depth model's per-frame scale and shift in
    /// its own output space). Needs the frame's normalised map
    /// ([`crate::Calibration::align`] gives it) and a store with
    /// [`AnchorStore::with_normalised`]; target `calibration-output` only.
    PredictionAffine,
}

impl std::fmt::Display for CorrectionModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::ScaleShift => "scale-shift",
            Self::Planar => "planar",
            Self::PredictionAffine => "prediction-affine",
        })
    }
}

impl std::str::FromStr for CorrectionModel {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "scale-shift" => Ok(Self::ScaleShift),
            "planar" => Ok(Self::Planar),
            "prediction-affine" => Ok(Self::PredictionAffine),
            other => Err(CoreError::InvalidParameter(format!(
                "unknown re-alignment correction '{other}' (expected prediction-affine, \
                 scale-shift or planar)"
            ))),
        }
    }
}

/// What the correction is fitted to at the anchors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum AnchorTarget {
    /// The calibration frame's ground truth: also corrects the one-shot fit's own error on the
    /// background (which need not transfer to the objects).
    GroundTruth,
    /// The calibration's own one-shot result on the calibration frame: removes only the model's
    /// change since calibration (the per-frame fluctuation), the fit itself is kept. Needs
    /// [`AnchorStore::with_one_shot`].
    #[default]
    CalibrationOutput,
}

impl std::fmt::Display for AnchorTarget {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::GroundTruth => "ground-truth",
            Self::CalibrationOutput => "calibration-output",
        })
    }
}

impl std::str::FromStr for AnchorTarget {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "ground-truth" => Ok(Self::GroundTruth),
            "calibration-output" => Ok(Self::CalibrationOutput),
            other => Err(CoreError::InvalidParameter(format!(
                "unknown re-alignment target '{other}' (expected calibration-output or ground-truth)"
            ))),
        }
    }
}

/// Settings of the re-alignment (module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RealignConfig {
    /// The anchor rule's thresholds.
    pub thresholds: AnchorThresholds,
    /// Correction form.
    pub model: CorrectionModel,
    /// What the correction is fitted to.
    pub target: AnchorTarget,
    /// Ridge λ towards the identity, in anchor equivalents (default 100; with the default 200
    /// anchors a strong shrinkage, chosen for `scale-shift` by the ablation in
    /// docs/evaluation.md; the `prediction-affine` tables there use λ = 1 and 2000 anchors).
    pub ridge: f64,
    /// Most anchors used (seeded subsample; default 200).
    pub max_anchors: usize,
    /// Fewest anchors (before the split) for a correction to be tried (default 50).
    pub min_anchors: usize,
    /// Fewest anchors as a fraction of the store's pixels with valid static depth (default
    /// 0.05): below it the frame is treated as covered — chance matches of a new surface that
    /// resembles the background must not decide the correction.
    pub min_anchor_fraction: f64,
    /// Fraction of the used anchors held out to accept or reject the correction (default 0.3).
    pub holdout_fraction: f64,
    /// Acceptance margin: the mean paired held-out gain (|error before| − |error after|, metres,
    /// [`HELD_OUT_TRIM`] trimmed) must exceed this many of its standard errors (default 1; 0
    /// accepts any gain). A correction that only fits noise gains nothing on held-out anchors
    /// on average and is rejected most of the time.
    pub acceptance_se: f64,
    /// Seed of the subsample and the split.
    pub seed: u64,
}

impl Default for RealignConfig {
    fn default() -> Self {
        Self {
            thresholds: AnchorThresholds::default(),
            model: CorrectionModel::ScaleShift,
            target: AnchorTarget::default(),
            ridge: 100.0,
            max_anchors: 200,
            min_anchors: 50,
            min_anchor_fraction: 0.05,
            holdout_fraction: 0.3,
            acceptance_se: 1.0,
            seed: 0,
        }
    }
}

impl RealignConfig {
    /// Checks the ranges.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the field.
    pub fn validate(&self) -> Result<()> {
        let t = &self.thresholds;
        if !(t.abs_grey.is_finite() && t.abs_grey >= 0.0 && t.rel.is_finite() && t.rel >= 0.0) {
            return Err(CoreError::InvalidParameter(
                "anchor thresholds must be finite and >= 0".into(),
            ));
        }
        if !(self.ridge.is_finite() && self.ridge >= 0.0) {
            return Err(CoreError::InvalidParameter(format!(
                "re-alignment ridge {} must be finite and >= 0",
                self.ridge
            )));
        }
        if !(self.acceptance_se.is_finite() && self.acceptance_se >= 0.0) {
            return Err(CoreError::InvalidParameter(format!(
                "re-alignment acceptance_se {} must be finite and >= 0",
                self.acceptance_se
            )));
        }
        if !(self.holdout_fraction > 0.0 && self.holdout_fraction < 1.0) {
            return Err(CoreError::InvalidParameter(format!(
                "re-alignment holdout fraction {} must be in (0, 1)",
                self.holdout_fraction
            )));
        }
        if !(0.0..1.0).contains(&self.min_anchor_fraction) {
            return Err(CoreError::InvalidParameter(format!(
                "re-alignment min_anchor_fraction {} must be in [0, 1)",
                self.min_anchor_fraction
            )));
        }
        if self.min_anchors < 10 || self.max_anchors < self.min_anchors {
            return Err(CoreError::InvalidParameter(format!(
                "re-alignment needs min_anchors >= 10 and max_anchors >= min_anchors (got {} and {})",
                self.min_anchors, self.max_anchors
            )));
        }
        Ok(())
    }
}

/// What re-alignment did to one frame. Never NaN: absent quantities are `None`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RealignReport {
    /// Anchor pixels found (half resolution, before subsampling).
    pub anchors: usize,
    /// Anchors used for fitting and the held-out test (after subsampling and dropping pixels
    /// without a one-shot depth).
    pub anchors_used: usize,
    /// Global brightness gain k of the frame against the calibration (None: no usable pixel).
    pub brightness_gain: Option<f64>,
    /// RMSE of the one-shot result on the held-out anchors, metres.
    pub held_out_rmse_before_m: Option<f64>,
    /// RMSE of the corrected result on the held-out anchors, metres.
    pub held_out_rmse_after_m: Option<f64>,
    /// Mean paired held-out gain |error before| − |error after|, metres ([`HELD_OUT_TRIM`]
    /// trimmed; positive: the correction helps), and its standard error.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out_gain_m: Option<f64>,
    /// Standard error of [`RealignReport::held_out_gain_m`], metres.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out_gain_se_m: Option<f64>,
    /// The correction form that was tried.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub correction: Option<CorrectionModel>,
    /// What the correction was fitted to at the anchors, and so what the held-out RMSEs
    /// measure: the frame's change since calibration (`calibration-output`, the default and
    /// the value of reports written before the field existed) or its error against the
    /// calibration frame's ground truth.
    #[serde(default)]
    pub target: AnchorTarget,
    /// The accepted `prediction-affine` map ẑ' = a·ẑ + b as `[a, b]` (absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prediction_affine: Option<[f64; 2]>,
    /// Whether the correction was applied.
    pub accepted: bool,
    /// Why (a warning when not accepted).
    pub reason: String,
    /// RMSE of the depth this frame gets against the **calibration frame's ground truth** at
    /// anchors that no fit used, metres, trimmed as the held-out RMSEs: the frame's own error
    /// on the unchanged background, whatever the `target`. A kept one-shot result: the
    /// subsample's anchors and up to 2 000 of the rest (evenly through them). Corrected: those
    /// 2 000 outside the fitted subsample (`max_anchors`), or, where fewer remain than were
    /// held out, the held-out anchors with the correction fitted without them. The frame's
    /// error model takes its flat σ from it ([`crate::Calibration::frame_error_model`]);
    /// absent in reports written before the field existed and where no correction could be
    /// fitted (too few anchors, a degenerate fit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out_truth_rmse_m: Option<f64>,
    /// The same errors in inverse depth, `|1/z − 1/z_truth|`, 1/m (trimmed RMSE): what an
    /// error model whose σ grows as z² in metres needs at its reference depth.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out_truth_inverse_rmse_per_m: Option<f64>,
}

/// Anchors of one frame: full-resolution pixels with their calibration depth.
#[derive(Debug, Clone, PartialEq)]
pub struct Anchors {
    /// `(u, v, z_m, one_shot_m)`: column, row (full resolution, pixels), calibration ground
    /// truth and the calibration's one-shot result there (metres; NaN when not stored).
    pub pixels: Vec<(u32, u32, f32, f32)>,
    /// Global brightness gain (None: no usable pixel to estimate it).
    pub gain: Option<f64>,
}

/// Finds the anchors of a frame with grey `grey` (from its RGB; module documentation, rule 1–4).
///
/// # Errors
/// Size mismatch with the store.
pub fn find_anchors(
    store: &AnchorStore,
    grey: &GreyHalf,
    thresholds: &AnchorThresholds,
) -> Result<Anchors> {
    store.size.expect_eq("frame RGB", grey.size())?;
    let (hh, hw) = half(store.size);
    let gf = grey.as_slice();
    let gc = store
        .grey
        .as_slice()
        .ok_or_else(|| CoreError::InvalidParameter("anchor store grey is not contiguous".into()))?;
    let mut ratios: Vec<f32> = gc
        .iter()
        .zip(gf)
        .step_by(7)
        .filter(|&(&c, &f)| (20..=235).contains(&c) && (1.0..=250.0).contains(&f))
        .map(|(&c, &f)| f / c as f32)
        .collect();
    let Some(k) = median_in_place(&mut ratios) else {
        return Ok(Anchors {
            pixels: Vec::new(),
            gain: None,
        });
    };
    if !(MIN_GAIN..=MAX_GAIN).contains(&k) {
        // an implausible exposure change (lens covered, lights off): a gain this far from 1
        // compresses the calibration's texture below the tolerance, so no pixel is trusted
        return Ok(Anchors {
            pixels: Vec::new(),
            gain: Some(k as f64),
        });
    }
    // rules 2–4 at the candidate pixels (every ANCHOR_STRIDE-th half-resolution pixel in each
    // direction): for some displacement s, every pixel q of the 3×3 patch around p must match,
    // |g_f(q) − k·g_c(q + s)| ≤ abs + rel·k·g_c(q); tests stop at the first mismatch.
    let depth = store.depth_mm.as_slice().ok_or_else(|| {
        CoreError::InvalidParameter("anchor store depth is not contiguous".into())
    })?;
    let one_shot = store.one_shot_mm.as_ref().and_then(|a| a.as_slice());
    let (abs, rel) = (thresholds.abs_grey, thresholds.rel * k);
    let mut pixels = Vec::new();
    for i in (1..hh.saturating_sub(1)).step_by(ANCHOR_STRIDE) {
        for j in (1..hw.saturating_sub(1)).step_by(ANCHOR_STRIDE) {
            let d = depth[i * hw + j];
            if d == 0 {
                continue;
            }
            let matches = |di: isize, dj: isize| {
                for a in i - 1..=i + 1 {
                    let sa = (a as isize + di).clamp(0, hh as isize - 1) as usize;
                    for b in j - 1..=j + 1 {
                        let sb = (b as isize + dj).clamp(0, hw as isize - 1) as usize;
                        let f = gf[a * hw + b];
                        let tol = abs + rel * gc[a * hw + b] as f32;
                        if f > 250.0 || (f - k * gc[sa * hw + sb] as f32).abs() > tol {
                            return false;
                        }
                    }
                }
                true
            };
            // the undisplaced patch first (the common case for an unchanged pixel)
            let unchanged = matches(0, 0)
                || [
                    (-1, -1),
                    (-1, 0),
                    (-1, 1),
                    (0, -1),
                    (0, 1),
                    (1, -1),
                    (1, 0),
                    (1, 1),
                ]
                .iter()
                .any(|&(di, dj)| matches(di, dj));
            if unchanged {
                let o = one_shot.map_or(0, |a| a[i * hw + j]);
                let o = if o > 0 { o as f32 * 1e-3 } else { f32::NAN };
                pixels.push(((2 * j) as u32, (2 * i) as u32, d as f32 * 1e-3, o));
            }
        }
    }
    Ok(Anchors {
        pixels,
        gain: Some(k as f64),
    })
}

/// One anchor ready for fitting: pixel, ground-truth target and one-shot target.
#[derive(Debug, Clone, Copy)]
struct Obs {
    u: f64,
    v: f64,
    /// The calibration frame's ground truth here, metres (NaN when not stored).
    gt_m: f64,
    z_m: f64,
    t: f64,
    y: f64,
}

/// A fitted correction δ = y₀·c·f(y, u, v) in the alignment space (module documentation).
#[derive(Debug, Clone, Copy)]
struct Correction {
    model: CorrectionModel,
    y0: f64,
    width: f64,
    height: f64,
    c: [f64; 4],
}

impl Correction {
    fn features(&self, y: f64, u: f64, v: f64) -> [f64; 4] {
        let s = y / self.y0;
        match self.model {
            CorrectionModel::ScaleShift | CorrectionModel::PredictionAffine => [s, 1.0, 0.0, 0.0],
            CorrectionModel::Planar => [
                s,
                1.0,
                s * (u / self.width - 0.5),
                s * (v / self.height - 0.5),
            ],
        }
    }

    fn delta(&self, y: f64, u: f64, v: f64) -> f64 {
        let f = self.features(y, u, v);
        self.y0 * (self.c[0] * f[0] + self.c[1] * f[1] + self.c[2] * f[2] + self.c[3] * f[3])
    }

    /// Ridge least squares on `obs`; `None` when the system is singular.
    fn fit(model: CorrectionModel, size: ImageSize, obs: &[Obs], ridge: f64) -> Option<Self> {
        let y0 = obs.iter().map(|o| o.y).sum::<f64>() / obs.len().max(1) as f64;
        if !(y0.is_finite() && y0 > 0.0) {
            return None;
        }
        let mut c = Self {
            model,
            y0,
            width: size.width as f64,
            height: size.height as f64,
            c: [0.0; 4],
        };
        let mut a = nalgebra::Matrix4::<f64>::zeros();
        let mut b = nalgebra::Vector4::<f64>::zeros();
        for o in obs {
            let f = c.features(o.y, o.u, o.v);
            let r = (o.t - o.y) / y0;
            for p in 0..4 {
                b[p] += f[p] * r;
                for q in 0..4 {
                    a[(p, q)] += f[p] * f[q];
                }
            }
        }
        // unused features: identity rows keep the system regular (their coefficient stays 0)
        let used = match model {
            CorrectionModel::ScaleShift | CorrectionModel::PredictionAffine => 2,
            CorrectionModel::Planar => 4,
        };
        for p in 0..4 {
            a[(p, p)] += if p < used { ridge.max(1e-9) } else { 1.0 };
        }
        let sol = a.cholesky()?.solve(&b);
        c.c = [sol[0], sol[1], sol[2], sol[3]];
        c.c.iter().all(|x| x.is_finite()).then_some(c)
    }

    /// Fit, one trimming pass (3 robust standard deviations), refit.
    fn fit_trimmed(
        model: CorrectionModel,
        size: ImageSize,
        obs: &[Obs],
        ridge: f64,
    ) -> Option<Self> {
        let first = Self::fit(model, size, obs, ridge)?;
        let mut res: Vec<f32> = obs
            .iter()
            .map(|o| (o.t - o.y - first.delta(o.y, o.u, o.v)) as f32)
            .collect();
        let med = median_in_place(&mut res.clone())?;
        for r in res.iter_mut() {
            *r = (*r - med).abs();
        }
        let mad = median_in_place(&mut res.clone())? as f64;
        let thr = (3.0 * 1.4826 * mad).max(1e-12);
        let kept: Vec<Obs> = obs
            .iter()
            .zip(&res)
            .filter(|&(_, &r)| (r as f64) <= thr)
            .map(|(o, _)| *o)
            .collect();
        if kept.len() == obs.len() || kept.len() < 4 {
            return Some(first);
        }
        Self::fit(model, size, &kept, ridge)
    }
}

/// Absolute error of a depth against its reference, metres; an invalid depth counts with the
/// full reference depth.
fn abs_err_m(z: f64, z_ref: f64) -> f64 {
    if z.is_finite() && z > 0.0 {
        (z - z_ref).abs()
    } else {
        z_ref
    }
}

/// Absolute error of a depth against its reference in inverse depth, 1/m; an invalid depth
/// counts as infinitely far (the reference's whole inverse depth).
fn abs_err_inverse_per_m(z: f64, z_ref: f64) -> f64 {
    if z.is_finite() && z > 0.0 {
        (1.0 / z - 1.0 / z_ref).abs()
    } else {
        1.0 / z_ref
    }
}

/// The held-out observations with their depth, metres, of the one-shot result (`corr` None)
/// or the corrected one.
fn held_depths_m<'a>(
    obs: &'a [Obs],
    space: AlignSpace,
    corr: Option<&'a Correction>,
) -> impl Iterator<Item = (f64, &'a Obs)> + 'a {
    obs.iter().map(move |o| {
        let t = match corr {
            Some(c) => o.y + c.delta(o.y, o.u, o.v),
            None => o.y,
        };
        (space.depth_from_target(t), o)
    })
}

/// Held-out absolute errors, metres, of the one-shot result (`corr` None) or the corrected one.
fn errors_m(obs: &[Obs], space: AlignSpace, corr: Option<&Correction>) -> Vec<f64> {
    held_depths_m(obs, space, corr)
        .map(|(z, o)| abs_err_m(z, o.z_m))
        .collect()
}

/// Fills [`RealignReport::held_out_truth_rmse_m`] and its inverse-depth twin from `(depth,
/// calibration ground truth)` pairs at anchors no fit used, metres (pairs without a ground
/// truth are left out; both `None` when none is left).
fn set_truth_residual(report: &mut RealignReport, pairs: impl Iterator<Item = (f64, f64)>) {
    let (metres, inverse): (Vec<f64>, Vec<f64>) = pairs
        .filter(|&(_, gt)| gt.is_finite() && gt > 0.0)
        .map(|(z, gt)| (abs_err_m(z, gt), abs_err_inverse_per_m(z, gt)))
        .unzip();
    let some = !metres.is_empty();
    report.held_out_truth_rmse_m = some.then(|| trimmed_rmse(&metres));
    report.held_out_truth_inverse_rmse_per_m = some.then(|| trimmed_rmse(&inverse));
}

/// The RMSE of absolute errors without the largest [`HELD_OUT_TRIM`] fraction of them (a few
/// false anchors, e.g. on a new object of the background's grey, must not decide).
fn trimmed_rmse(errors: &[f64]) -> f64 {
    let mut e2: Vec<f64> = errors.iter().map(|e| e * e).collect();
    e2.sort_by(f64::total_cmp);
    let keep =
        ((e2.len() as f64 * (1.0 - HELD_OUT_TRIM)).ceil() as usize).clamp(1, e2.len().max(1));
    (e2.iter().take(keep).sum::<f64>() / keep as f64).sqrt()
}

/// Mean paired gain `before − after` of absolute held-out errors and its standard error, over
/// the held-out anchors without the [`HELD_OUT_TRIM`] fraction with the largest error before or
/// after.
fn paired_gain(before: &[f64], after: &[f64]) -> (f64, f64) {
    let n = before.len().min(after.len());
    if n == 0 {
        return (0.0, 0.0);
    }
    let mut idx: Vec<usize> = (0..n).collect();
    idx.sort_by(|&a, &b| before[a].max(after[a]).total_cmp(&before[b].max(after[b])));
    let keep = ((n as f64 * (1.0 - HELD_OUT_TRIM)).ceil() as usize).clamp(1, n);
    let d: Vec<f64> = idx[..keep].iter().map(|&i| before[i] - after[i]).collect();
    let k = d.len() as f64;
    let mean = d.iter().sum::<f64>() / k;
    if d.len() < 2 {
        return (mean, 0.0);
    }
    let var = d.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (k - 1.0);
    (mean, (var / k).sqrt())
}

/// Fills the held-out part of the report and decides acceptance (module documentation).
fn decide(report: &mut RealignReport, before: &[f64], after: &[f64], acceptance_se: f64) -> bool {
    let (rb, ra) = (trimmed_rmse(before), trimmed_rmse(after));
    let (gain, se) = paired_gain(before, after);
    report.held_out_rmse_before_m = Some(rb);
    report.held_out_rmse_after_m = Some(ra);
    report.held_out_gain_m = Some(gain);
    report.held_out_gain_se_m = Some(se);
    let ok = gain > 0.0 && gain > acceptance_se * se;
    if !ok {
        report.reason = format!(
            "kept the one-shot result: the correction does not lower the held-out error enough \
             (RMSE {:.2} mm -> {:.2} mm; mean gain {:.3} mm, standard error {:.3} mm, needs > {} \
             standard error(s))",
            rb * 1e3,
            ra * 1e3,
            gain * 1e3,
            se * 1e3,
            acceptance_se
        );
    }
    ok
}

/// Fraction of the largest held-out errors left out of the held-out RMSE and of the paired
/// gain.
pub const HELD_OUT_TRIM: f64 = 0.1;

/// The fewest anchors a frame needs (module documentation).
fn anchors_needed(store: &AnchorStore, config: &RealignConfig) -> usize {
    config
        .min_anchors
        .max((config.min_anchor_fraction * store.candidate_px() as f64).ceil() as usize)
}

fn too_few_reason(have: usize, need: usize, store: &AnchorStore, grey: &GreyHalf) -> String {
    // an over-exposed image has no texture to match: say so rather than blame the scene
    let frame = grey.as_slice();
    let frame_sat = saturated_share(frame.iter().copied(), frame.len());
    let calib_sat = store.saturated_share();
    let why = if frame_sat.max(calib_sat) >= SATURATED_WARN_SHARE {
        let (what, s) = if frame_sat >= calib_sat {
            ("the frame's", frame_sat)
        } else {
            ("the calibration frame's", calib_sat)
        };
        format!(
            "{:.0} % of {what} image is saturated (grey above {SATURATED_GREY}): over-exposed, \
             lower the camera's exposure or gain",
            s * 100.0
        )
    } else {
        "background covered or changed, camera moved, or lighting changed locally".to_string()
    };
    format!("kept the one-shot result: {have} usable anchor(s), need {need} ({why})")
}

/// The share of `n` grey values above [`SATURATED_GREY`].
fn saturated_share(grey: impl Iterator<Item = f32>, n: usize) -> f64 {
    grey.filter(|&g| g > SATURATED_GREY).count() as f64 / n.max(1) as f64
}

/// Grey level above which an anchor pixel is saturated (module documentation, rule 2).
pub const SATURATED_GREY: f32 = 250.0;

/// Share of saturated pixels from which too few anchors are put down to over-exposure (and
/// `moma calibrate --anchors` warns).
pub const SATURATED_WARN_SHARE: f64 = 0.3;

/// The seeded subsample of at most `max_anchors` and the number held out (the first ones).
fn subsample<T: Copy>(mut obs: Vec<T>, config: &RealignConfig) -> Subsample<T> {
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let take = config.max_anchors.min(obs.len());
    let (chosen, rest) = obs.partial_shuffle(&mut rng, take);
    // every k-th of the rest, at most TRUTH_ANCHORS of them: a σ to about 2 % (an LWLR
    // prediction-affine map costs ~0.1 µs per anchor, and a frame can have 50 000)
    let step = rest.len().div_ceil(TRUTH_ANCHORS).max(1);
    let (chosen, unused) = (
        chosen.to_vec(),
        rest.iter().step_by(step).copied().collect(),
    );
    let n_hold = ((chosen.len() as f64 * config.holdout_fraction).round() as usize)
        .clamp(1, chosen.len().saturating_sub(4).max(1));
    Subsample {
        chosen,
        unused,
        n_hold,
    }
}

/// The most anchors outside the fitted subsample on which [`RealignReport::held_out_truth_rmse_m`]
/// is measured.
const TRUTH_ANCHORS: usize = 2000;

/// The anchors a re-alignment works with: `chosen` (at most `max_anchors`, seeded), of which
/// the first `n_hold` are held out of the trial fit, and `unused`, up to [`TRUTH_ANCHORS`]
/// spread over the rest, which no fit sees.
struct Subsample<T> {
    chosen: Vec<T>,
    unused: Vec<T>,
    n_hold: usize,
}

impl<T> Subsample<T> {
    /// Where a kept one-shot result is measured against the calibration's truth
    /// ([`RealignReport::held_out_truth_rmse_m`]): every anchor, as no correction is applied.
    fn all(&self) -> impl Iterator<Item = &T> {
        self.chosen.iter().chain(&self.unused)
    }

    /// Where a corrected result is: the anchors no fit used, `None` when there are fewer of
    /// them than held-out ones (the held-out anchors with the trial correction then measure it).
    fn unfitted(&self) -> Option<&[T]> {
        (self.unused.len() >= self.n_hold).then_some(&self.unused[..])
    }
}

fn empty_report(anchors: &Anchors, model: CorrectionModel, target: AnchorTarget) -> RealignReport {
    RealignReport {
        anchors: anchors.pixels.len(),
        anchors_used: 0,
        brightness_gain: anchors.gain,
        held_out_rmse_before_m: None,
        held_out_rmse_after_m: None,
        held_out_gain_m: None,
        held_out_gain_se_m: None,
        correction: Some(model),
        target,
        prediction_affine: None,
        accepted: false,
        reason: String::new(),
        held_out_truth_rmse_m: None,
        held_out_truth_inverse_rmse_per_m: None,
    }
}

/// Re-aligns a one-shot result in place on the anchors of the frame with grey `grey` (from its
/// RGB) with an output-space correction (`scale-shift`, `planar`); `depth_m`
/// holds the one-shot metres (NaN where none) and is changed only when the correction is
/// accepted. `space` is the calibration's alignment space.
///
/// # Errors
/// Size mismatches with the store, an invalid `config`, the `prediction-affine` form (it needs
/// the frame's normalised prediction: [`realign_prediction_affine`]). Too few anchors or a
/// rejected correction are not errors: the report says so and `depth_m` is unchanged.
pub fn realign_in_place(
    store: &AnchorStore,
    grey: &GreyHalf,
    space: AlignSpace,
    config: &RealignConfig,
    depth_m: &mut ArrayViewMut2<'_, f32>,
) -> Result<RealignReport> {
    config.validate()?;
    if config.model == CorrectionModel::PredictionAffine {
        return Err(CoreError::InvalidParameter(
            "the prediction-affine re-alignment needs the frame's normalised prediction: use \
             Calibration::align with AlignOptions::realign"
                .into(),
        ));
    }
    store
        .size
        .expect_eq("one-shot depth", ImageSize::of(&depth_m.view()))?;
    if config.target == AnchorTarget::CalibrationOutput && !store.has_one_shot() {
        return Err(CoreError::InvalidParameter(
            "re-alignment target calibration-output needs the calibration's one-shot result in \
             the anchor store (AnchorStore::with_one_shot); this store holds only ground truth"
                .into(),
        ));
    }
    let anchors = find_anchors(store, grey, &config.thresholds)?;
    let mut report = empty_report(&anchors, config.model, config.target);
    let obs: Vec<Obs> = anchors
        .pixels
        .iter()
        .filter_map(|&(u, v, gt, cal)| {
            let z = match config.target {
                AnchorTarget::GroundTruth => gt,
                AnchorTarget::CalibrationOutput => cal,
            };
            let d = depth_m[[v as usize, u as usize]];
            let y = space.target_from_depth(d as f64);
            (is_valid_depth(d) && is_valid_depth(z) && y.is_finite()).then(|| Obs {
                u: u as f64,
                v: v as f64,
                gt_m: gt as f64,
                z_m: z as f64,
                t: space.target_from_depth(z as f64),
                y,
            })
        })
        .collect();
    let need = anchors_needed(store, config);
    if obs.len() < need {
        report.anchors_used = obs.len();
        report.reason = too_few_reason(obs.len(), need, store, grey);
        return Ok(report);
    }
    let sub = subsample(obs, config);
    let obs = &sub.chosen;
    report.anchors_used = obs.len();
    let (held, train) = obs.split_at(sub.n_hold);
    // the kept one-shot result against the calibration frame's truth
    // (`RealignReport::held_out_truth_rmse_m`)
    let truth_of_one_shot = |report: &mut RealignReport| {
        set_truth_residual(
            report,
            sub.all().map(|o| (space.depth_from_target(o.y), o.gt_m)),
        );
    };
    let Some(trial) = Correction::fit_trimmed(config.model, store.size, train, config.ridge) else {
        report.reason =
            "kept the one-shot result: the correction is degenerate on these anchors".into();
        return Ok(report);
    };
    let before = errors_m(held, space, None);
    let after = errors_m(held, space, Some(&trial));
    if !decide(&mut report, &before, &after, config.acceptance_se) {
        truth_of_one_shot(&mut report);
        return Ok(report);
    }
    let Some(fin) = Correction::fit_trimmed(config.model, store.size, obs, config.ridge) else {
        report.reason =
            "kept the one-shot result: the correction is degenerate on all anchors".into();
        truth_of_one_shot(&mut report);
        return Ok(report);
    };
    if fin.model == CorrectionModel::ScaleShift {
        // t̂ = (1 + c₀)·y + c₁·y₀: one affine map of the target for every pixel
        let (a, b) = ((1.0 + fin.c[0]) as f32, (fin.c[1] * fin.y0) as f32);
        match space {
            AlignSpace::Depth => depth_m.mapv_inplace(|z| {
                let t = a * z + b;
                if is_valid_depth(z) && is_valid_depth(t) {
                    t
                } else if is_valid_depth(z) {
                    f32::NAN
                } else {
                    z
                }
            }),
            AlignSpace::Inverse => depth_m.mapv_inplace(|z| {
                let t = a / z + b;
                if is_valid_depth(z) {
                    crate::kernels::depth_of_disparity(t)
                } else {
                    z
                }
            }),
        }
    } else {
        for ((v, u), d) in depth_m.indexed_iter_mut() {
            let z = *d as f64;
            if !is_valid_depth(*d) {
                continue;
            }
            let y = space.target_from_depth(z);
            let t = y + fin.delta(y, u as f64, v as f64);
            // Valid in f64 can still overflow f32 (e.g. a disparity of 1e-39 m⁻¹).
            let zc = space.depth_from_target(t) as f32;
            *d = if is_valid_depth(zc) { zc } else { f32::NAN };
        }
    }
    report.accepted = true;
    report.reason = accepted_reason(&report, obs.len());
    match sub.unfitted() {
        Some(unused) => set_truth_residual(
            &mut report,
            unused
                .iter()
                .map(|o| (f64::from(depth_m[[o.v as usize, o.u as usize]]), o.gt_m)),
        ),
        None => set_truth_residual(
            &mut report,
            held_depths_m(held, space, Some(&trial)).map(|(z, o)| (z, o.gt_m)),
        ),
    }
    Ok(report)
}

fn accepted_reason(report: &RealignReport, n: usize) -> String {
    format!(
        "corrected on {n} anchors: held-out RMSE {:.2} mm -> {:.2} mm (mean gain {:.3} mm, \
         standard error {:.3} mm)",
        report.held_out_rmse_before_m.unwrap_or(0.0) * 1e3,
        report.held_out_rmse_after_m.unwrap_or(0.0) * 1e3,
        report.held_out_gain_m.unwrap_or(0.0) * 1e3,
        report.held_out_gain_se_m.unwrap_or(0.0) * 1e3,
    )
}

/// One anchor of the `prediction-affine` fit: pixel, the frame's and the calibration frame's
/// normalised prediction, and the calibration's result there (metres).
#[derive(Debug, Clone, Copy)]
struct PredObs {
    u: f64,
    v: f64,
    x_new: f64,
    x_cal: f64,
    /// The calibration frame's ground truth here, metres (NaN when not stored).
    gt_m: f64,
    z_m: f64,
}

/// ẑ' = ẑ + c₀·R·(ẑ − m)/σ + R·c₁ (module documentation).
#[derive(Debug, Clone, Copy)]
struct PredAffine {
    m: f64,
    sd: f64,
    r: f64,
    c: [f64; 2],
}

impl PredAffine {
    fn apply(&self, x: f64) -> f64 {
        x + self.r * (self.c[0] * (x - self.m) / self.sd + self.c[1])
    }

    /// `(a, b)` of ẑ' = a·ẑ + b.
    fn ab(&self) -> (f64, f64) {
        let k = self.r * self.c[0] / self.sd;
        (1.0 + k, self.r * self.c[1] - k * self.m)
    }

    /// Ridge least squares of (x_cal − x_new)/R on [(x_new − m)/σ, 1].
    fn fit(obs: &[PredObs], r: f64, ridge: f64) -> Option<Self> {
        if obs.len() < 2 {
            return None;
        }
        let n = obs.len() as f64;
        let m = obs.iter().map(|o| o.x_new).sum::<f64>() / n;
        let sd = (obs.iter().map(|o| (o.x_new - m).powi(2)).sum::<f64>() / n).sqrt();
        if !(sd.is_finite() && sd > 0.0) {
            return None;
        }
        let (mut a00, mut a01, mut a11, mut b0, mut b1) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for o in obs {
            let f = (o.x_new - m) / sd;
            let y = (o.x_cal - o.x_new) / r;
            a00 += f * f;
            a01 += f;
            a11 += 1.0;
            b0 += f * y;
            b1 += y;
        }
        a00 += ridge.max(1e-9);
        a11 += ridge.max(1e-9);
        let det = a00 * a11 - a01 * a01;
        if !(det.is_finite() && det > 0.0) {
            return None;
        }
        let c = [(a11 * b0 - a01 * b1) / det, (a00 * b1 - a01 * b0) / det];
        (m.is_finite() && c.iter().all(|x| x.is_finite())).then_some(Self { m, sd, r, c })
    }

    /// Fit, one trimming pass (3 robust standard deviations), refit.
    fn fit_trimmed(obs: &[PredObs], r: f64, ridge: f64) -> Option<Self> {
        let first = Self::fit(obs, r, ridge)?;
        let mut res: Vec<f32> = obs
            .iter()
            .map(|o| (o.x_cal - first.apply(o.x_new)) as f32)
            .collect();
        let med = median_in_place(&mut res.clone())?;
        for x in res.iter_mut() {
            *x = (*x - med).abs();
        }
        let mad = median_in_place(&mut res.clone())? as f64;
        let thr = (3.0 * 1.4826 * mad).max(1e-12);
        let kept: Vec<PredObs> = obs
            .iter()
            .zip(&res)
            .filter(|&(_, &x)| (x as f64) <= thr)
            .map(|(o, _)| *o)
            .collect();
        if kept.len() == obs.len() || kept.len() < 4 {
            return Some(first);
        }
        Self::fit(&kept, r, ridge)
    }
}

/// The `prediction-affine` re-alignment of a frame (module documentation): finds the anchors of
/// the frame with grey `grey` (from its RGB), fits ẑ' = a·ẑ + b of the frame's normalised
/// prediction `normalised` so that it reproduces the calibration frame's normalised prediction
/// at the anchors, and decides on held-out anchors, measured in metres through `model` (the
/// calibration's alignment model, in `space`). Returns the report and `(a, b)` when accepted;
/// the caller applies the model to a·ẑ + b.
///
/// # Errors
/// Size mismatches with the store, an invalid `config`, a store without the calibration's
/// normalised prediction ([`AnchorStore::with_normalised`]), target `ground-truth`.
pub fn realign_prediction_affine(
    store: &AnchorStore,
    grey: &GreyHalf,
    model: &AlignmentModel,
    space: AlignSpace,
    config: &RealignConfig,
    normalised: ArrayView2<'_, f32>,
) -> Result<(RealignReport, Option<(f32, f32)>)> {
    config.validate()?;
    store
        .size
        .expect_eq("normalised prediction", ImageSize::of(&normalised))?;
    if config.target != AnchorTarget::CalibrationOutput {
        return Err(CoreError::InvalidParameter(format!(
            "the prediction-affine re-alignment reproduces the calibration frame's own \
             prediction (target calibration-output); target {} needs the scale-shift or planar \
             correction",
            config.target
        )));
    }
    let stored = store.normalised.as_ref().ok_or_else(|| {
        CoreError::InvalidParameter(
            "the anchor store holds no normalised calibration prediction (written before the \
             prediction-affine correction existed): calibrate again with --anchors, or choose \
             the scale-shift correction"
                .into(),
        )
    })?;
    let anchors = find_anchors(store, grey, &config.thresholds)?;
    let mut report = empty_report(&anchors, CorrectionModel::PredictionAffine, config.target);
    // R: the range of the calibration's normalised prediction, the scale over which the
    // correction is extrapolated from the anchors to the rest of the image
    let (lo, hi) = stored
        .iter()
        .filter(|x| x.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
            (lo.min(x as f64), hi.max(x as f64))
        });
    let r = hi - lo;
    let obs: Vec<PredObs> = anchors
        .pixels
        .iter()
        .filter_map(|&(u, v, gt, _)| {
            let x_new = normalised[[v as usize, u as usize]] as f64;
            let x_cal = stored[[v as usize / 2, u as usize / 2]] as f64;
            let (uf, vf) = (u as f64, v as f64);
            let z = space.depth_from_target(model.predict_at(uf, vf, x_cal));
            (x_new.is_finite() && x_cal.is_finite() && z.is_finite() && z > 0.0).then_some(
                PredObs {
                    u: uf,
                    v: vf,
                    x_new,
                    x_cal,
                    gt_m: gt as f64,
                    z_m: z,
                },
            )
        })
        .collect();
    let need = anchors_needed(store, config);
    if obs.len() < need {
        report.anchors_used = obs.len();
        report.reason = too_few_reason(obs.len(), need, store, grey);
        return Ok((report, None));
    }
    let sub = subsample(obs, config);
    let obs = &sub.chosen;
    report.anchors_used = obs.len();
    let (held, train) = obs.split_at(sub.n_hold);
    let trial = if r.is_finite() && r > 0.0 {
        PredAffine::fit_trimmed(train, r, config.ridge)
    } else {
        None
    };
    let Some(trial) = trial else {
        report.reason =
            "kept the one-shot result: the correction is degenerate on these anchors".into();
        return Ok((report, None));
    };
    let depth_at = |o: &PredObs, x: f64| space.depth_from_target(model.predict_at(o.u, o.v, x));
    let before: Vec<f64> = held
        .iter()
        .map(|o| abs_err_m(depth_at(o, o.x_new), o.z_m))
        .collect();
    let after: Vec<f64> = held
        .iter()
        .map(|o| abs_err_m(depth_at(o, trial.apply(o.x_new)), o.z_m))
        .collect();
    // the kept one-shot result against the calibration frame's truth
    // (`RealignReport::held_out_truth_rmse_m`)
    let truth_of_one_shot = |report: &mut RealignReport| {
        set_truth_residual(report, sub.all().map(|o| (depth_at(o, o.x_new), o.gt_m)));
    };
    if !decide(&mut report, &before, &after, config.acceptance_se) {
        truth_of_one_shot(&mut report);
        return Ok((report, None));
    }
    let Some(fin) = PredAffine::fit_trimmed(obs, r, config.ridge) else {
        report.reason =
            "kept the one-shot result: the correction is degenerate on all anchors".into();
        truth_of_one_shot(&mut report);
        return Ok((report, None));
    };
    let (measured, map) = match sub.unfitted() {
        Some(unused) => (unused, &fin),
        None => (held, &trial),
    };
    set_truth_residual(
        &mut report,
        measured
            .iter()
            .map(|o| (depth_at(o, map.apply(o.x_new)), o.gt_m)),
    );
    let (a, b) = fin.ab();
    report.accepted = true;
    report.prediction_affine = Some([a, b]);
    report.reason = accepted_reason(&report, obs.len());
    Ok((report, Some((a as f32, b as f32))))
}
