//! # moma-io — MOMA's file formats
//!
//! Everything MOMA reads or writes, with one error type ([`IoError`]) whose messages always
//! name the file and the problem, and one rule for output: every writer goes through
//! [`atomic_write`] (temporary file in the destination directory, then rename), so a failed
//! write never leaves a half-written file. Full format descriptions: `docs/formats.md`.
//!
//! | data | formats | read | write |
//! |---|---|---|---|
//! | metric depth (metres) | uint16 PNG in **millimetres** (0 = none), float32 `.npy` in metres, PFM in metres | [`read_depth`] | [`write_depth`] |
//! | raw predictions (unitless) | `.npy` (f32/f64), PFM, uint16 PNG (raw values) | [`read_prediction`] | [`write_prediction`] (`.npy`/`.pfm` only) |
//! | masks | PNG, nonzero = inside (8-bit canonical; 1/2/4/16-bit, RGB accepted) | [`read_mask`] | [`write_mask`] |
//! | RGB images | PNG / JPEG, 8-bit | [`read_rgb`] | [`write_rgb`] |
//! | intrinsics | `camera.json` `{"width","height","fx","fy","cx","cy"}` (pixels) | [`read_camera`] | [`write_camera`] |
//! | RGB-D sets | the "moma set" directory layout | [`MomaSet::open`] | [`MomaSetWriter`] |
//! | calibrations | versioned JSON (`moma-calibration` v1) | [`read_calibration`] | [`write_calibration`] |
//! | pictures | colour-mapped PNG (turbo/viridis) with its range in `tEXt` chunks; colour bar | [`read_colour_scale`] | [`write_depth_colormap`], [`colour_bar`] |
//! | limits | every decoder refuses headers claiming more than [`MAX_IMAGE_PIXELS`] pixels or [`MAX_IMAGE_SIDE_PX`] per side, or more data than the file holds, before allocating | [`check_image_size`] | — |
//! | point clouds | PLY, binary little-endian or ASCII, metres, camera frame | — | [`write_ply`], [`write_depth_ply`] |
//!
//! Metric depth and predictions are kept apart by type: [`write_depth`] accepts only a
//! [`MetricDepth`](moma_core::MetricDepth), and [`write_prediction`] refuses the millimetre PNG,
//! so uncalibrated output can never be written as metres.
//!
//! ## Example
//! ```
//! use moma_core::MetricDepth;
//! use ndarray::array;
//!
//! let dir = tempfile::tempdir()?;
//! let depth = MetricDepth::new(array![[0.5f32, 1.2344], [f32::NAN, 70.0]]);
//!
//! // uint16 millimetres: rounded to the nearest mm; NaN and > 65.535 m become 0 ("no measurement").
//! let stats = moma_io::write_depth(dir.path().join("depth.png"), &depth)?;
//! assert_eq!((stats.invalid, stats.out_of_range), (1, 1));
//! let back = moma_io::read_depth(dir.path().join("depth.png"))?;
//! assert_eq!(back.depth_m[[0, 1]], 1.234);
//! assert!(back.depth_m[[1, 1]].is_nan());
//!
//! // float32 metres: exact.
//! moma_io::write_depth(dir.path().join("depth.npy"), &depth)?;
//! assert_eq!(moma_io::read_depth(dir.path().join("depth.npy"))?.depth_m[[0, 1]], 1.2344);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod aligned;
mod anchors;
mod atomic;
pub mod batch;
mod calibration;
mod camera;
mod colormap;
mod depth;
mod draw;
mod error;
mod grey;
mod json_files;
mod limits;
mod ply;
mod png_util;
mod predictions;
mod raster;
mod set;

pub use aligned::{
    ALIGNED_FORMAT, ALIGNED_INDEX_FILE, ALIGNED_LOCK_FILE, ALIGNED_VERSION, AlignedFile,
    AlignedIndex, Provenance, aligned_index_path, provenance_of, read_aligned_index,
    record_aligned_files, record_before_writing, recorded_path,
};
pub use atomic::{atomic_write, remove_temporaries_in_flight, same_file};
pub use calibration::{
    CALIBRATION_FORMAT, CALIBRATION_VERSION, CalibrationFile, CreationInfo,
    OLDEST_CALIBRATION_VERSION, parse_calibration, read_calibration, write_calibration,
};
pub use camera::{parse_camera, read_camera, write_camera};
pub use colormap::{
    COLORMAP_ENTRIES, Colormap, ColourScale, DepthRange, TEXT_COLORMAP, TEXT_MAX_M, TEXT_MIN_M,
    colormap_index, colour_bar, colourise, colourise_depth, colourise_with, read_colour_scale,
    resolve_range, write_depth_colormap, write_sigma_colormap,
};
pub use depth::{
    DepthFormat, DepthWriteStats, PNG_DEPTH_MAX_M, PNG_DEPTH_UNITS_PER_M, PfmByteOrder,
    depth_to_mm, npy_f32_from_bytes, pfm_from_bytes, png16_from_bytes, read_depth,
    read_depth_sized, read_npy_f32, read_pfm, read_png16, read_prediction, write_depth,
    write_npy_f32, write_pfm, write_prediction,
};
pub use draw::{draw_segments, draw_segments_outlined};
pub use error::{IoError, Result};
pub use grey::grey_half;
pub use json_files::{
    ExtrinsicsFile, MAX_SETTINGS_JSON_BYTES, parse_json, read_extrinsics, read_json,
    write_extrinsics, write_json,
};
pub use limits::{DEFLATE_MAX_RATIO, MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE_PX, check_image_size};
pub use ply::{PlyFormat, ply_header, write_depth_ply, write_ply, write_scene_ply};
pub use predictions::{
    PREDICTIONS_FORMAT, PREDICTIONS_INDEX_FILE, PREDICTIONS_VERSION, PredictionIndex,
    PredictionIndexHead, prediction_index_listing, read_prediction_index,
    read_prediction_index_for, resolve_prediction_kind,
};
pub use raster::{
    JPEG_QUALITY, mask_from_bytes, read_mask, read_mask_sized, read_object_mask_sized,
    read_png_description, read_rgb, read_rgb_sized, rgb_from_bytes, rgb_size, write_mask,
    write_rgb, write_rgb_png_described,
};
pub use set::{
    CAMERA_FILE, DEPTH_FILE, FRAMES_DIR, Frame, FrameData, LoadedFrame, LoadedSet, MASK_FILE,
    MomaSet, MomaSetWriter, RAW_DEPTH_FILE, RGB_FILE, loaded_set_name,
};
