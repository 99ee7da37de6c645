//! Bad input: every case gets a clear error naming the file, and no output is left half-written.

use std::path::Path;

use moma_core::{AlignOptions, CalibrationFrame};
use moma_core::{ImageSize, Intrinsics, Mask, MetricDepth, Prediction, PredictionKind};
use moma_io::*;
use ndarray::{Array2, array};

/// The error and its sources joined by ": ", as the CLI prints them.
fn msg(e: &IoError) -> String {
    let mut parts = vec![e.to_string()];
    let mut source = std::error::Error::source(e);
    while let Some(s) = source {
        parts.push(s.to_string());
        source = s.source();
    }
    parts.join(": ")
}

fn write_small_png(path: &Path) {
    write_depth(
        path,
        &MetricDepth::new(Array2::from_shape_fn((32, 32), |(v, u)| {
            0.5 + (u * v) as f32 * 1e-3
        })),
    )
    .unwrap();
}

/// Entries of `dir` (hidden temporary files included).
fn entries(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn truncated_png_is_corrupt() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.png");
    write_small_png(&good);
    let bytes = std::fs::read(&good).unwrap();
    let p = dir.path().join("truncated.png");
    std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
    for e in [
        read_depth(&p).unwrap_err(),
        read_mask(&p).unwrap_err(),
        read_rgb(&p).unwrap_err(),
    ] {
        assert!(matches!(e, IoError::Corrupt { .. }), "{e}");
        assert!(
            msg(&e).contains("truncated.png") && msg(&e).contains("PNG"),
            "{e}"
        );
    }
    // Garbage with a .png name.
    let g = dir.path().join("garbage.png");
    std::fs::write(&g, b"definitely not a png").unwrap();
    let e = read_depth(&g).unwrap_err();
    assert!(
        matches!(e, IoError::Corrupt { .. }) && msg(&e).contains("garbage.png"),
        "{e}"
    );
    let e = read_rgb(&g).unwrap_err();
    assert!(msg(&e).contains("garbage.png"), "{e}");
}

#[test]
fn missing_file_names_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("nope.png");
    let e = read_depth(&p).unwrap_err();
    assert!(
        matches!(e, IoError::Io { .. }) && msg(&e).contains("nope.png"),
        "{e}"
    );
    assert_eq!(e.path(), p);
}

#[test]
fn eight_bit_png_is_not_depth() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("m.png");
    write_mask(&p, &Mask::full(ImageSize::new(3, 2))).unwrap();
    let e = read_depth(&p).unwrap_err();
    assert!(matches!(e, IoError::Unsupported { .. }), "{e}");
    assert!(
        msg(&e).contains("m.png") && msg(&e).contains("16-bit"),
        "{e}"
    );
    assert!(read_prediction(&p, PredictionKind::MetricDepth).is_err());
}

#[test]
fn a_depth_png_is_not_an_rgb_image() {
    // Passing the frame's depth.png where its rgb.png belongs (e.g. `--realign-rgb`) used to be
    // read as a dark grey image and silently gave no anchors.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("depth.png");
    write_depth(&p, &MetricDepth::new(array![[0.5f32, 0.7], [0.0, 1.2]])).unwrap();
    let e = read_rgb(&p).unwrap_err();
    assert!(matches!(e, IoError::Invalid { .. }), "{e}");
    assert!(
        msg(&e).contains("depth.png") && msg(&e).contains("16-bit single-channel"),
        "{e}"
    );
    // 8-bit grey stays a grey frame.
    let q = dir.path().join("grey.png");
    write_mask(&q, &Mask::full(ImageSize::new(3, 2))).unwrap();
    assert_eq!(read_rgb(&q).unwrap().get_pixel(0, 0).0, [255, 255, 255]);
}

#[test]
fn corrupt_and_truncated_npy() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.npy");
    write_npy_f32(&good, Array2::<f32>::ones((8, 8)).view()).unwrap();
    let bytes = std::fs::read(&good).unwrap();

    let p = dir.path().join("truncated.npy");
    std::fs::write(&p, &bytes[..bytes.len() - 10]).unwrap();
    let e = read_depth(&p).unwrap_err();
    assert!(matches!(e, IoError::Corrupt { .. }), "{e}");
    assert!(
        msg(&e).contains("truncated.npy") && msg(&e).contains("truncated"),
        "{e}"
    );

    let p = dir.path().join("bad_magic.npy");
    let mut b = bytes.clone();
    b[1] = b'X';
    std::fs::write(&p, &b).unwrap();
    let e = read_depth(&p).unwrap_err();
    assert!(
        matches!(e, IoError::Corrupt { .. }) && msg(&e).contains("bad_magic.npy"),
        "{e}"
    );

    let p = dir.path().join("header_only.npy");
    std::fs::write(&p, &bytes[..20]).unwrap();
    let e = read_depth(&p).unwrap_err();
    assert!(
        matches!(e, IoError::Corrupt { .. }) && msg(&e).contains("header_only.npy"),
        "{e}"
    );

    let p = dir.path().join("extra.npy");
    let mut b = bytes.clone();
    b.extend_from_slice(&[0, 0, 0, 0]);
    std::fs::write(&p, &b).unwrap();
    assert!(matches!(
        read_depth(&p).unwrap_err(),
        IoError::Corrupt { .. }
    ));
}

#[test]
fn wrong_dtype_npy_is_unsupported() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("ints.npy");
    ndarray_npy::write_npy(&p, &Array2::<i32>::zeros((2, 2))).unwrap();
    let e = read_depth(&p).unwrap_err();
    assert!(matches!(e, IoError::Unsupported { .. }), "{e}");
    let m = msg(&e);
    assert!(
        m.contains("ints.npy") && m.contains("<i4") && m.contains("float32"),
        "{m}"
    );
    let p = dir.path().join("u16.npy");
    ndarray_npy::write_npy(&p, &Array2::<u16>::zeros((2, 2))).unwrap();
    assert!(msg(&read_prediction(&p, PredictionKind::MetricDepth).unwrap_err()).contains("<u2"));
}

/// A float map of millimetres (a sensor PNG cast to float without dividing by 1000) is refused
/// by its median, in both float formats; the same map in metres, and one with a few far
/// outliers, reads (the bound is the median, not the maximum).
#[test]
fn float_depth_in_millimetres_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mm = Array2::from_shape_fn((6, 8), |(r, c)| 600.0 + (r * 8 + c) as f32);
    for name in ["mm.npy", "mm.pfm"] {
        let p = dir.path().join(name);
        moma_io::write_depth(&p, &moma_core::MetricDepth::new(mm.clone())).unwrap();
        let e = read_depth(&p).unwrap_err();
        assert!(matches!(e, IoError::Invalid { .. }), "{e}");
        let m = msg(&e);
        assert!(
            m.contains(name) && m.contains("median depth 624 m looks like millimetres"),
            "{m}"
        );
        let metres = mm.mapv(|z| z / 1000.0);
        moma_io::write_depth(&p, &moma_core::MetricDepth::new(metres.clone())).unwrap();
        assert_eq!(read_depth(&p).unwrap().depth_m, metres);
        let mut outliers = metres.clone();
        outliers.row_mut(0).fill(5000.0);
        moma_io::write_depth(&p, &moma_core::MetricDepth::new(outliers.clone())).unwrap();
        assert_eq!(read_depth(&p).unwrap().depth_m, outliers);
    }
}

/// The reverse mistake: metres written into a millimetre PNG (a scene 0.6–0.65 m away stored as
/// 0 and 1), and metres divided by 1000 into a float file, are refused by their median; a
/// near object in a plausible scene still reads.
#[test]
fn depth_that_is_not_metres_by_being_too_near_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let metres = Array2::from_shape_fn((6, 8), |(r, c)| 0.6 + 0.001 * (r * 8 + c) as f32);
    // a uint16 PNG of round(metres): 1 where valid (1 mm), as a user's cast would give
    let png = dir.path().join("as_metres.png");
    let ones = metres.mapv(|z| z.round());
    moma_io::write_depth(
        &png,
        &moma_core::MetricDepth::new(ones.mapv(|z| z / 1000.0)),
    )
    .unwrap();
    let m = msg(&read_depth(&png).unwrap_err());
    assert!(
        m.contains("as_metres.png") && m.contains("median depth 1.0 mm") && m.contains("metres"),
        "{m}"
    );
    for name in ["km.npy", "km.pfm"] {
        let p = dir.path().join(name);
        let km = metres.mapv(|z| z / 1000.0);
        moma_io::write_depth(&p, &moma_core::MetricDepth::new(km)).unwrap();
        let m = msg(&read_depth(&p).unwrap_err());
        assert!(
            m.contains(name) && m.contains("median depth 0.6 mm") && m.contains("kilometres"),
            "{m}"
        );
        // metres read; and a few pixels of an object 1 cm away do not move the median
        let mut near = metres.clone();
        near.row_mut(0).fill(0.01);
        moma_io::write_depth(&p, &moma_core::MetricDepth::new(near.clone())).unwrap();
        assert_eq!(read_depth(&p).unwrap().depth_m, near);
    }
}

#[test]
fn unknown_depth_extension() {
    let e = read_depth("/tmp/whatever.exr").unwrap_err();
    assert!(
        msg(&e).contains("whatever.exr") && msg(&e).contains("exr"),
        "{e}"
    );
}

#[test]
fn truncated_pfm() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("d.pfm");
    write_pfm(
        &p,
        Array2::<f32>::ones((4, 4)).view(),
        PfmByteOrder::BigEndian,
    )
    .unwrap();
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() - 3]).unwrap();
    let e = read_depth(&p).unwrap_err();
    assert!(
        matches!(e, IoError::Corrupt { .. })
            && msg(&e).contains("d.pfm")
            && msg(&e).contains("truncated"),
        "{e}"
    );
}

#[test]
fn prediction_refuses_millimetre_png() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("pred.png");
    let e = write_prediction(
        &p,
        &Prediction::new(Array2::ones((2, 2)), PredictionKind::RelativeDisparity),
    )
    .unwrap_err();
    assert!(matches!(e, IoError::Unsupported { .. }), "{e}");
    assert!(
        msg(&e).contains("pred.png") && msg(&e).contains("metric depth only"),
        "{e}"
    );
    assert!(!p.exists());
}

#[test]
fn camera_json_errors() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("camera.json");
    std::fs::write(
        &p,
        "{\n  \"width\": 640,\n  \"height\": 480,\n  \"fx\": 500.0,\n  \"cx\": 320\n}\n",
    )
    .unwrap();
    let e = read_camera(&p).unwrap_err();
    let m = msg(&e);
    assert!(
        matches!(e, IoError::Json { .. })
            && m.contains("camera.json")
            && m.contains("missing field `fy`"),
        "{m}"
    );

    std::fs::write(
        &p,
        r#"{"width":640,"height":480,"fx":-1,"fy":500,"cx":320,"cy":240}"#,
    )
    .unwrap();
    let e = read_camera(&p).unwrap_err();
    assert!(
        matches!(e, IoError::Core { .. })
            && msg(&e).contains("camera.json")
            && msg(&e).contains("fx"),
        "{e}"
    );

    std::fs::write(
        &p,
        r#"{"width":640,"height":480,"fx":500,"fy":0,"cx":320,"cy":240}"#,
    )
    .unwrap();
    assert!(msg(&read_camera(&p).unwrap_err()).contains("fy"));

    std::fs::write(
        &p,
        r#"{"width":0,"height":480,"fx":500,"fy":500,"cx":320,"cy":240}"#,
    )
    .unwrap();
    assert!(matches!(read_camera(&p).unwrap_err(), IoError::Core { .. }));

    std::fs::write(&p, r#"{"width":640,"height":480,"fx":"500","#).unwrap();
    let e = read_camera(&p).unwrap_err();
    assert!(matches!(e, IoError::Json { line: 1, .. }), "{e}");

    // Writing invalid intrinsics is refused too, and leaves nothing.
    let q = dir.path().join("out.json");
    let bad = Intrinsics {
        width: 4,
        height: 4,
        fx: 0.0,
        fy: 1.0,
        cx: 0.0,
        cy: 0.0,
    };
    assert!(write_camera(&q, &bad).is_err());
    assert!(!q.exists());
}

#[test]
fn mask_size_mismatch() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("mask.png");
    write_mask(&p, &Mask::full(ImageSize::new(5, 4))).unwrap();
    let e = read_mask_sized(&p, ImageSize::new(640, 480)).unwrap_err();
    assert!(matches!(e, IoError::SizeMismatch { .. }), "{e}");
    let m = msg(&e);
    assert!(
        m.contains("mask.png") && m.contains("5x4") && m.contains("640x480"),
        "{m}"
    );
    assert!(read_depth_sized(dir.path().join("mask.png"), ImageSize::new(5, 4)).is_err());
}

mod calibration {
    use super::*;
    use moma_core::align::{AlignmentModel, FitReport, SampleSet};
    use moma_core::pipeline::Calibration;

    /// `f` written to `p`, and the JSON it wrote (to edit and write back).
    fn written_json(p: &Path, f: &CalibrationFile) -> serde_json::Value {
        write_calibration(p, f).unwrap();
        serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
    }

    fn file() -> CalibrationFile {
        let calibration = Calibration {
            normalisation: moma_core::NormalisationConfig {
                method: moma_core::Normalisation::None,
                space: moma_core::AlignSpace::Depth,
            },
            prediction_kind: PredictionKind::MetricDepth,
            model: AlignmentModel::Raw,
            report: FitReport {
                method: moma_core::align::MethodName::Raw,
                n_used: 0,
                rms_residual_m: 0.0,
                fit_time_s: 0.0,
                robust: None,
            },
            samples: SampleSet {
                space: moma_core::normalise::AlignSpace::Depth,
                image_size: ImageSize::new(8, 6),
                samples: vec![],
            },
            workspace: None,
            anchors: None,
            error_model: None,
            normalisation_notes: Vec::new(),
        };
        CalibrationFile::new(calibration, None, CreationInfo::now())
    }

    /// A version-1 file as moma 0.1 wrote it (GSSA, minmax, workspace given as a path).
    fn v1_text(workspace: &str, inverse_space: bool) -> String {
        format!(
            r#"{{"format":"moma-calibration","version":1,"method":"gssa",
            "normalisation":{{"method":"minmax","inverse_space":{inverse_space}}},
            "prediction_kind":"inverse-depth",
            "calibration":{{"normalisation":{{"method":"minmax","inverse_space":{inverse_space}}},
              "prediction_kind":"inverse-depth",
              "model":{{"method":"gssa","scale":0.5,"shift":0.25}},
              "report":{{"method":"gssa","n_used":2,"rms_residual_m":0.001,"fit_time_s":1e-6}},
              "samples":{{"image_size":{{"width":8,"height":6}},"samples":[
                {{"u":1.0,"v":2.0,"pred":0.3,"depth_m":0.8}},{{"u":5.0,"v":4.0,"pred":0.6,"depth_m":0.9}}]}}}},
            "intrinsics":null,"image_size":{{"width":8,"height":6}},"workspace_mask":{workspace},
            "created":{{"moma_version":"0.1.0","created_unix_s":1700000000,"command_line":[],"sources":{{}}}}}}"#
        )
    }

    #[test]
    fn version_1_files_are_migrated() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        std::fs::write(&p, v1_text("null", false)).unwrap();
        let f = read_calibration(&p).unwrap();
        assert_eq!(f.version, moma_io::CALIBRATION_VERSION);
        assert_eq!(f.normalisation.space, moma_core::AlignSpace::Depth);
        assert!(f.calibration.workspace.is_none());
        // a workspace path (relative to the file) is read and embedded
        let mask = moma_core::Mask::new(ndarray::Array2::from_shape_fn((6, 8), |(v, _)| v > 1));
        moma_io::write_mask(dir.path().join("ws.png"), &mask).unwrap();
        std::fs::write(&p, v1_text("\"ws.png\"", false)).unwrap();
        let f = read_calibration(&p).unwrap();
        assert_eq!(f.calibration.workspace.unwrap().mask(), &mask);
        // a missing workspace file, and the dropped --inverse-space mode, are clear errors
        std::fs::write(&p, v1_text("\"/nonexistent/ws.png\"", false)).unwrap();
        let m = msg(&read_calibration(&p).unwrap_err());
        assert!(
            m.contains("version-1") && m.contains("/nonexistent/ws.png"),
            "{m}"
        );
        std::fs::write(&p, v1_text("null", true)).unwrap();
        let m = msg(&read_calibration(&p).unwrap_err());
        assert!(
            m.contains("--inverse-space") && m.contains("moma calibrate"),
            "{m}"
        );
    }

    fn gssa_file_value() -> serde_json::Value {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        std::fs::write(&p, v1_text("null", false)).unwrap();
        let f = read_calibration(&p).unwrap();
        serde_json::to_value(&f).unwrap()
    }

    fn read_value(v: &serde_json::Value) -> String {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        std::fs::write(&p, serde_json::to_string(v).unwrap()).unwrap();
        msg(&read_calibration(&p).unwrap_err())
    }

    #[test]
    fn unknown_fields_nan_and_bad_parameters_are_refused() {
        let mut v = gssa_file_value();
        v["extra"] = serde_json::json!(true);
        let m = read_value(&v);
        assert!(
            m.contains("unknown field `extra`") && m.contains("calib.json"),
            "{m}"
        );
        let mut v = gssa_file_value();
        v["calibration"]["model"]["surprise"] = serde_json::json!(1);
        assert!(read_value(&v).contains("unknown field `surprise`"));
        // JSON has no NaN: a parameter written as null or a string is a schema error
        let mut v = gssa_file_value();
        v["calibration"]["model"]["scale"] = serde_json::Value::Null;
        assert!(read_value(&v).contains("calib.json"));
        // an absurd (overflowing) value becomes infinite and is refused by validation
        let text = serde_json::to_string(&gssa_file_value())
            .unwrap()
            .replace("\"scale\":0.5", "\"scale\":1e999");
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        std::fs::write(&p, text).unwrap();
        let m = msg(&read_calibration(&p).unwrap_err());
        assert!(
            m.contains("not a finite number") || m.contains("calib.json"),
            "{m}"
        );
        // an inconsistent summary field
        let mut v = gssa_file_value();
        v["method"] = serde_json::json!("ssra");
        assert!(read_value(&v).contains("inconsistent"));
    }

    #[test]
    fn truncated_json_names_file_line_and_column() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        write_calibration(&p, &file()).unwrap();
        let text = std::fs::read_to_string(&p).unwrap();
        // cut mid-line (a cut right after a newline reports column 0)
        std::fs::write(&p, text[..text.len() * 2 / 3].trim_end()).unwrap();
        let e = read_calibration(&p).unwrap_err();
        let IoError::Json { line, column, .. } = &e else {
            panic!("{e}")
        };
        assert!(*line > 1 && *column > 0);
        let m = msg(&e);
        assert!(
            m.contains("calib.json") && m.contains("line") && m.contains("truncated"),
            "{m}"
        );
    }

    #[test]
    fn corrupt_json() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        std::fs::write(
            &p,
            "{\n  \"format\": \"moma-calibration\",\n  \"version\": 1,,\n}",
        )
        .unwrap();
        let e = read_calibration(&p).unwrap_err();
        assert!(matches!(e, IoError::Json { line: 3, .. }), "{e}");
        std::fs::write(&p, "").unwrap();
        assert!(matches!(
            read_calibration(&p).unwrap_err(),
            IoError::Json { .. }
        ));
    }

    #[test]
    fn version_2_to_8_files_read_as_version_9() {
        // Versions 3, 4, 6, 7, 8 and 9 only added optional fields and version 5 renamed the
        // kinds: the same document (without them) labelled 2 to 8 must read, equal.
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        let mut v = written_json(&p, &file());
        let written = read_calibration(&p).unwrap();
        assert_eq!(v["version"], 9);
        for old in [2, 3, 4, 5, 6, 7, 8] {
            v["version"] = old.into();
            std::fs::write(&p, v.to_string()).unwrap();
            let read = read_calibration(&p).unwrap();
            assert_eq!(read.calibration, written.calibration);
            assert_eq!(read.version, 9);
        }
    }

    /// An error model field added in a file version, across versions: a calibration holding
    /// `model` is written, the file carries `field` = `written` and reads back equal; labelled
    /// `old_version` without `field`, the file reads, and that model is returned; at the current
    /// version with `field` = `bad`, reading fails, and the message is returned.
    fn error_model_field_across_versions(
        model: moma_core::DepthErrorModel,
        field: &str,
        written: serde_json::Value,
        old_version: u32,
        bad: serde_json::Value,
    ) -> (moma_core::DepthErrorModel, String) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        let mut f = file();
        f.calibration.error_model = Some(model);
        let mut v = written_json(&p, &f);
        assert_eq!(v["calibration"]["error_model"][field], written);
        assert_eq!(read_calibration(&p).unwrap(), f);
        v["version"] = old_version.into();
        v["calibration"]["error_model"]
            .as_object_mut()
            .unwrap()
            .remove(field);
        std::fs::write(&p, v.to_string()).unwrap();
        let back = read_calibration(&p)
            .unwrap()
            .calibration
            .error_model
            .unwrap();
        v["version"] = moma_io::CALIBRATION_VERSION.into();
        v["calibration"]["error_model"][field] = bad;
        std::fs::write(&p, v.to_string()).unwrap();
        (back, msg(&read_calibration(&p).unwrap_err()))
    }

    /// Version 9 added the error model's `sample_distance_gain`: written and read back; a
    /// version-8 file's model (without it) reads with none (no distance part); out of range is
    /// refused, naming the field.
    #[test]
    fn a_version_8_error_model_reads_without_a_distance_part() {
        let mut model = moma_core::DepthErrorModel::uniform(0.005).unwrap();
        model.sample_distance_gain = 1e-4;
        let (back, m) = error_model_field_across_versions(
            model,
            "sample_distance_gain",
            serde_json::json!(1e-4),
            8,
            serde_json::json!(-1e-4),
        );
        assert_eq!(back.sample_distance_gain, 0.0);
        assert!(m.contains("sample_distance_gain"), "{m}");
    }

    /// Version 8 added the error model's `height_sigma`: written and read back; a version-7
    /// file's model (without it) reads with none (no height part); out of range is refused,
    /// naming the field.
    #[test]
    fn a_version_7_error_model_reads_without_a_height_part() {
        let mut model = moma_core::DepthErrorModel::uniform(0.005).unwrap();
        model.height_sigma = 0.12;
        let (back, m) = error_model_field_across_versions(
            model,
            "height_sigma",
            serde_json::json!(0.12),
            7,
            serde_json::json!(-0.5),
        );
        assert_eq!(back.height_sigma, 0.0);
        assert_eq!(back.sigma_flat_m, 0.005);
        assert!(
            m.contains("calib.json") && m.contains("height_sigma"),
            "{m}"
        );
    }

    /// Version 7 added the error model's `sigma_dense_m`: written and read back; a version-6
    /// file's model (without it) reads with none, so that its `sigma_flat_m` stands in; out of
    /// range is refused, naming the field.
    #[test]
    fn a_version_6_error_model_reads_without_its_dense_sigma() {
        let mut model = moma_core::DepthErrorModel::uniform(0.006).unwrap();
        model.sigma_dense_m = Some(0.002);
        let (back, m) = error_model_field_across_versions(
            model,
            "sigma_dense_m",
            serde_json::json!(0.002),
            6,
            serde_json::json!(f64::MAX),
        );
        assert_eq!(back.sigma_dense_m, None);
        assert_eq!(back.sigma_flat_m, 0.006);
        assert!(
            m.contains("calib.json") && m.contains("sigma_dense_m"),
            "{m}"
        );
    }

    /// Version 6 added the error model's `relief_max_m`: a version-5 file's error model (without
    /// it) reads with the 0.1 m every earlier build used, and a written file carries it; out of
    /// range is refused, naming the field.
    #[test]
    fn a_version_5_error_model_reads_with_the_old_relief_range() {
        let mut model = moma_core::DepthErrorModel::uniform(0.004).unwrap();
        model.relief_bias = 0.2;
        model.relief_max_m = 0.4;
        let (back, m) = error_model_field_across_versions(
            model,
            "relief_max_m",
            serde_json::json!(0.4),
            5,
            serde_json::json!(-1.0),
        );
        assert_eq!(back.relief_max_m, 0.1);
        assert_eq!(back.relief_bias, 0.2);
        assert_eq!(back.sigma_dense_m, None);
        assert!(
            m.contains("calib.json") && m.contains("relief_max_m"),
            "{m}"
        );
    }

    /// docs/formats.md "Prediction kinds": a version-1 to -4 file's `depth` is `metric-depth`
    /// for `raw` (it used the prediction as metres) and `relative-depth` otherwise;
    /// `inverse-depth` is `relative-disparity`. A version-5 file is written with the new name.
    #[test]
    fn old_kind_names_are_mapped_on_reading() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        let with_kind = |v: &mut serde_json::Value, kind: &str| {
            v["prediction_kind"] = kind.into();
            v["calibration"]["prediction_kind"] = kind.into();
        };
        // raw + depth → metric-depth
        let mut raw = written_json(&p, &file());
        assert_eq!(raw["prediction_kind"], "metric-depth");
        raw["version"] = 4.into();
        with_kind(&mut raw, "depth");
        std::fs::write(&p, raw.to_string()).unwrap();
        let read = read_calibration(&p).unwrap();
        assert_eq!(read.prediction_kind, PredictionKind::MetricDepth);
        assert_eq!(
            read.calibration.prediction_kind,
            PredictionKind::MetricDepth
        );
        // the v1 GSSA file: inverse-depth → relative-disparity, depth → relative-depth
        let mut v1: serde_json::Value = serde_json::from_str(&v1_text("null", false)).unwrap();
        for (old, new) in [
            ("inverse-depth", PredictionKind::RelativeDisparity),
            ("depth", PredictionKind::RelativeDepth),
        ] {
            with_kind(&mut v1, old);
            std::fs::write(&p, v1.to_string()).unwrap();
            let read = read_calibration(&p).unwrap();
            assert_eq!(
                (read.prediction_kind, read.calibration.prediction_kind),
                (new, new)
            );
            // the parameter named `shift_m` before version 5 is the model's `shift`
            assert!(
                matches!(read.calibration.model, AlignmentModel::Gssa(m) if m.shift == 0.25),
                "{:?}",
                read.calibration.model
            );
            // written back under the new name, and read back equal
            let q = dir.path().join("rewritten.json");
            write_calibration(&q, &read).unwrap();
            let text: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&q).unwrap()).unwrap();
            assert_eq!(text["prediction_kind"], new.name());
            assert_eq!(read_calibration(&q).unwrap(), read);
        }
        // an unknown name is refused, naming the three
        with_kind(&mut v1, "metres");
        std::fs::write(&p, v1.to_string()).unwrap();
        let m = msg(&read_calibration(&p).unwrap_err());
        assert!(
            m.contains("metres") && m.contains("relative-disparity"),
            "{m}"
        );
    }

    #[test]
    fn an_error_model_out_of_range_is_refused_naming_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        let mut f = file();
        f.calibration.error_model = Some(moma_core::DepthErrorModel::uniform(0.004).unwrap());
        let mut v = written_json(&p, &f);
        assert_eq!(read_calibration(&p).unwrap(), f);
        v["calibration"]["error_model"]["variance_shares"] =
            serde_json::json!([0.5, 0.5, 0.5, 0.5]);
        std::fs::write(&p, v.to_string()).unwrap();
        let m = msg(&read_calibration(&p).unwrap_err());
        assert!(
            m.contains("calib.json") && m.contains("variance shares"),
            "{m}"
        );
        v["calibration"]["error_model"]["variance_shares"] =
            serde_json::json!([0.0, 0.0, 0.0, 1.0]);
        v["calibration"]["error_model"]["sigma_flat_m"] = serde_json::json!(-0.1);
        std::fs::write(&p, v.to_string()).unwrap();
        let m = msg(&read_calibration(&p).unwrap_err());
        assert!(m.contains("sigma_flat_m"), "{m}");
    }

    #[test]
    fn unknown_version_or_format() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        let mut v = written_json(&p, &file());
        v["version"] = 10.into();
        // A v10 file may have a different schema: the version error must win over schema errors.
        v["calibration"] = serde_json::json!({"something": "new"});
        std::fs::write(&p, v.to_string()).unwrap();
        let e = read_calibration(&p).unwrap_err();
        assert!(matches!(e, IoError::CalibrationVersion { .. }), "{e}");
        let m = msg(&e);
        assert!(
            m.contains("calib.json") && m.contains("version 10") && m.contains("versions 1 to 9"),
            "{m}"
        );

        v["version"] = 1.into();
        v["format"] = "something-else".into();
        std::fs::write(&p, v.to_string()).unwrap();
        assert!(msg(&read_calibration(&p).unwrap_err()).contains("something-else"));

        std::fs::write(&p, r#"{"width": 640}"#).unwrap();
        let m = msg(&read_calibration(&p).unwrap_err());
        assert!(m.contains("<missing>"), "{m}");

        // the version as text: said to be text, not read as the supported number
        let mut v = written_json(&p, &file());
        v["version"] = "9".into();
        std::fs::write(&p, v.to_string()).unwrap();
        let m = msg(&read_calibration(&p).unwrap_err());
        assert!(m.contains("version \"9\" (text, not a number)"), "{m}");
    }

    /// Edits that make a file's parts disagree: samples outside the image, a report that
    /// counts other samples, a negative residual. Each refused naming what is wrong.
    #[test]
    fn edited_samples_and_report_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        let mut good = written_json(&p, &file());
        // two samples inside the 8 × 6 image, counted by the report: a good file
        good["calibration"]["samples"]["samples"] = serde_json::json!([
            {"u": 1.0, "v": 1.0, "pred": 0.7, "depth_m": 0.7},
            {"u": 7.0, "v": 5.0, "pred": 0.9, "depth_m": 0.9}
        ]);
        good["calibration"]["report"]["n_used"] = 2.into();
        std::fs::write(&p, good.to_string()).unwrap();
        assert_eq!(read_calibration(&p).unwrap().calibration.samples.len(), 2);
        type Edit = fn(&mut serde_json::Value);
        let cases: [(&str, Edit); 4] = [
            (
                "outside the",
                (|v| v["calibration"]["samples"]["samples"][0]["u"] = 1e6.into()),
            ),
            (
                "samples were used",
                (|v| v["calibration"]["samples"]["samples"] = serde_json::json!([])),
            ),
            (
                "rms_residual_m",
                (|v| v["calibration"]["report"]["rms_residual_m"] = (-5.0).into()),
            ),
            (
                "outside the",
                (|v| v["calibration"]["samples"]["samples"][0]["v"] = (-1.0).into()),
            ),
        ];
        for (says, edit) in cases {
            let mut v = good.clone();
            edit(&mut v);
            std::fs::write(&p, v.to_string()).unwrap();
            let m = msg(&read_calibration(&p).unwrap_err());
            assert!(m.contains(says) && m.contains("calib.json"), "{says}: {m}");
        }
    }

    #[test]
    fn inconsistent_summary_fields() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        let mut v = written_json(&p, &file());
        v["prediction_kind"] = "inverse-depth".into();
        std::fs::write(&p, v.to_string()).unwrap();
        let e = read_calibration(&p).unwrap_err();
        assert!(
            matches!(e, IoError::Invalid { .. }) && msg(&e).contains("prediction_kind"),
            "{e}"
        );
        // Writing an inconsistent file is refused as well.
        let mut f = file();
        f.method = moma_core::align::MethodName::Ssra;
        let q = dir.path().join("q.json");
        assert!(write_calibration(&q, &f).is_err());
        assert!(!q.exists());
    }

    /// A calibration of `method` (inverse-depth prediction, inverse space) on a small tilted
    /// table with a box, as the JSON value a file holds.
    fn fitted_value(method: &str) -> serde_json::Value {
        let (h, w) = (24, 32);
        let gt = MetricDepth::new(Array2::from_shape_fn((h, w), |(v, u)| {
            let table = 0.6 + 0.004 * u as f32 + 0.002 * v as f32;
            if (8..16).contains(&v) && (10..20).contains(&u) {
                table - 0.05
            } else {
                table
            }
        }));
        let pred = Prediction::new(
            gt.depth_m.mapv(|z| 1.0 / z - 0.4),
            PredictionKind::RelativeDisparity,
        );
        let config = moma_core::pipeline::CalibrationConfig {
            method: method.parse().unwrap(),
            normalisation: moma_core::NormalisationConfig::native(
                moma_core::Normalisation::Minmax,
                PredictionKind::RelativeDisparity,
            ),
            sampling: moma_core::sampling::SamplingConfig {
                n: 60,
                ..Default::default()
            },
            robust: None,
            workspace: None,
        };
        let c =
            moma_core::pipeline::calibrate(&[CalibrationFrame::new(&pred, &gt)], &config).unwrap();
        serde_json::to_value(CalibrationFile::new(c, None, CreationInfo::now())).unwrap()
    }

    /// Reads the calibration file `v` and aligns the ramp 0.5 + 0.01·(u + 2v) (inverse depth,
    /// 32×24) with it.
    fn try_read_and_align(v: &serde_json::Value) -> Result<Array2<f32>, moma_core::CoreError> {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        std::fs::write(&p, v.to_string()).unwrap();
        let c = read_calibration(&p).unwrap().calibration;
        let values = Array2::from_shape_fn((24, 32), |(v, u)| 0.5 + 0.01 * (u + 2 * v) as f32);
        c.aligned(
            &Prediction::new(values, PredictionKind::RelativeDisparity),
            &AlignOptions::default(),
        )
        .map(|a| a.depth.depth_m)
    }

    fn read_and_align(v: &serde_json::Value) -> Array2<f32> {
        try_read_and_align(v).unwrap()
    }

    #[test]
    fn a_model_claiming_a_huge_image_is_refused_before_its_grid_is_built() {
        // 0xAAAA…AB · 3 wraps to 1 in 64 bits: a wrapped pixel count would pass every size
        // limit. Found by `moma-fuzz --target calibration-apply`: validating the local model
        // first built its node grid over 2^63 columns and aborted on the allocation.
        let huge = serde_json::json!({"width": 0xAAAA_AAAA_AAAA_AAABu64, "height": 3});
        assert_eq!(
            ImageSize::new(0xAAAA_AAAA_AAAA_AAAB, 3).pixels(),
            usize::MAX
        );
        for method in ["ssra-local", "gssa-local", "lwlr", "ssra"] {
            // Only the model's size: a mismatch with the calibration's.
            let mut v = fitted_value(method);
            v["calibration"]["model"]["image_size"] = huge.clone();
            let m = read_value(&v);
            assert!(
                m.contains("calib.json") && m.contains("alignment model"),
                "{method}: {m}"
            );
            // Every size field: too large.
            v["image_size"] = huge.clone();
            v["calibration"]["samples"]["image_size"] = huge.clone();
            let m = read_value(&v);
            assert!(
                m.contains("calib.json") && m.contains("too large"),
                "{method}: {m}"
            );
        }
    }

    #[test]
    fn a_disparity_too_small_to_invert_is_invalid_not_infinite_metres() {
        // Inverse space: GSSA's fitted disparity 0.5·ẑ + 1e-45 m⁻¹ is subnormal where ẑ = 0
        // (the prediction's minimum under minmax-unit), and 1/1e-45 overflows f32.
        let mut v = fitted_value("gssa");
        v["normalisation"]["method"] = serde_json::json!("minmax-unit");
        v["calibration"]["normalisation"]["method"] = serde_json::json!("minmax-unit");
        v["calibration"]["model"]["scale"] = serde_json::json!(0.5);
        v["calibration"]["model"]["shift"] = serde_json::json!(1e-45);
        let depth = read_and_align(&v);
        assert!(depth[[0, 0]].is_nan(), "{}", depth[[0, 0]]);
        assert!(depth.iter().all(|z| !z.is_infinite()));
        // Every other pixel: 1 / (0.5·ẑ) with ẑ = (x − min) / (max − min).
        let (lo, hi) = (0.5f64, 0.5 + 0.01 * (31 + 2 * 23) as f64);
        let x = 0.5 + 0.01 * 5.0;
        let want = 1.0 / (0.5 * (x - lo) / (hi - lo));
        assert!(
            (f64::from(depth[[0, 5]]) - want).abs() < 1e-4 * want,
            "{} vs {want}",
            depth[[0, 5]]
        );
    }

    #[test]
    fn parameters_that_overflow_f32_give_invalid_pixels_not_infinite_metres() {
        // Finite in f64 (so the file is valid JSON and passes the finiteness checks), but the
        // alignment runs in f32: the products overflow.
        for space in ["depth", "inverse"] {
            for (scale, shift) in [(1e308, 0.1), (-1e308, 0.1), (0.2, 1e308), (3e38, 0.0)] {
                let mut v = fitted_value("gssa");
                v["normalisation"]["space"] = serde_json::json!(space);
                v["calibration"]["normalisation"]["space"] = serde_json::json!(space);
                v["calibration"]["model"]["scale"] = serde_json::json!(scale);
                v["calibration"]["model"]["shift"] = serde_json::json!(shift);
                let what = format!("{space} space, scale {scale:e}, shift {shift:e}");
                let depth = match try_read_and_align(&v) {
                    // refused: no pixel of positive depth, or metres a hundred times off the
                    // calibration's ground truth (`PLAUSIBLE_OUTPUT_FACTOR`)
                    Err(e) => {
                        assert!(
                            matches!(
                                e,
                                moma_core::CoreError::NoValidPixels(_)
                                    | moma_core::CoreError::Degenerate(_)
                            ),
                            "{what}: {e}"
                        );
                        continue;
                    }
                    Ok(depth) => depth,
                };
                assert!(depth.iter().all(|z| !z.is_infinite()), "{what}");
                // In inverse space a huge disparity is a depth of about 0 m: invalid, never 0.
                assert!(depth.iter().all(|&z| z != 0.0), "{what}");
                assert!(depth.iter().any(|z| z.is_nan()), "{what}");
            }
        }
    }

    #[test]
    fn non_finite_numbers_are_not_written() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.json");
        let mut f = file();
        f.calibration.report.rms_residual_m = f64::NAN;
        let e = write_calibration(&p, &f).unwrap_err();
        assert!(
            msg(&e).contains("NaN") && msg(&e).contains("calib.json"),
            "{e}"
        );
        assert!(!p.exists());
    }
}

/// An empty map is refused by every writer (no reader would take the file back), and nothing
/// is left behind.
#[test]
fn empty_maps_are_not_written() {
    let dir = tempfile::tempdir().unwrap();
    for (h, w) in [(0, 0), (0, 3), (3, 0)] {
        let depth = MetricDepth::new(Array2::<f32>::zeros((h, w)));
        let pred = Prediction::new(Array2::<f32>::zeros((h, w)), PredictionKind::RelativeDepth);
        for ext in ["npy", "pfm", "png"] {
            let p = dir.path().join(format!("d.{ext}"));
            let e = write_depth(&p, &depth).unwrap_err();
            assert!(msg(&e).contains(&format!("d.{ext}")), "{e}");
            assert!(!p.exists(), "{ext} {h}x{w}");
        }
        for ext in ["npy", "pfm"] {
            let p = dir.path().join(format!("p.{ext}"));
            assert!(write_prediction(&p, &pred).is_err(), "{ext} {h}x{w}");
            assert!(!p.exists());
        }
    }
    assert!(entries(dir.path()).is_empty());
}

#[test]
fn output_into_missing_directory_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("no_such_dir").join("out.png");
    let depth = MetricDepth::new(array![[1.0f32]]);
    let e = write_depth(&p, &depth).unwrap_err();
    assert!(msg(&e).contains("no_such_dir"), "{e}");
    assert!(!p.exists());
    assert!(entries(dir.path()).is_empty());
    // A file in place of the directory.
    let f = dir.path().join("a_file");
    std::fs::write(&f, "x").unwrap();
    assert!(write_depth(f.join("out.npy"), &depth).is_err());
    assert!(write_mask(f.join("m.png"), &Mask::full(ImageSize::new(1, 1))).is_err());
    assert_eq!(entries(dir.path()), ["a_file"]);
}

#[test]
fn output_in_unwritable_directory_leaves_nothing() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let ro = dir.path().join("ro");
    std::fs::create_dir(&ro).unwrap();
    std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
    if std::fs::write(ro.join("probe"), "x").is_ok() {
        // Running as root: permissions are not enforced; the atomicity is covered elsewhere.
        eprintln!(
            "SKIP output_in_unwritable_directory_leaves_nothing: permissions not enforced (root?)"
        );
        std::fs::remove_file(ro.join("probe")).unwrap();
    } else {
        let p = ro.join("calib.npy");
        let e = write_depth(&p, &MetricDepth::new(array![[1.0f32]])).unwrap_err();
        assert!(
            matches!(e, IoError::Io { .. }) && msg(&e).contains("calib.npy"),
            "{e}"
        );
        assert!(entries(&ro).is_empty());
    }
    std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o755)).unwrap();
}

#[test]
fn failed_write_keeps_old_file_and_no_temporary() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("keep.txt");
    std::fs::write(&p, "old").unwrap();
    let r: Result<()> = atomic_write(&p, |w| {
        w.write_all(b"partial new content").unwrap();
        Err(IoError::Invalid {
            path: p.clone(),
            message: "simulated failure".into(),
        })
    });
    assert!(r.is_err());
    assert_eq!(std::fs::read_to_string(&p).unwrap(), "old");
    assert_eq!(entries(dir.path()), ["keep.txt"]);
    // A directory in the way is refused before anything is written.
    let d = dir.path().join("is_a_dir.npy");
    std::fs::create_dir(&d).unwrap();
    let e = write_depth(&d, &MetricDepth::new(array![[1.0f32]])).unwrap_err();
    assert!(
        msg(&e).contains("is a directory (give the name of a file"),
        "{e}"
    );
    assert_eq!(entries(dir.path()), ["is_a_dir.npy", "keep.txt"]);
    // a "directory" that is a file is named as such, not as missing
    let e = write_depth(p.join("d.npy"), &MetricDepth::new(array![[1.0f32]])).unwrap_err();
    assert!(msg(&e).contains("is a file, not a directory"), "{e}");
    let e = write_depth(
        dir.path().join("absent").join("d.npy"),
        &MetricDepth::new(array![[1.0f32]]),
    )
    .unwrap_err();
    assert!(msg(&e).contains("does not exist"), "{e}");
}

#[test]
fn written_files_have_ordinary_permissions() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("d.npy");
    write_depth(&p, &MetricDepth::new(array![[1.0f32]])).unwrap();
    let mode = std::fs::metadata(&p).unwrap().permissions().mode() & 0o777;
    assert!(
        mode & 0o044 != 0,
        "mode {mode:o} should be readable by others (0666 minus umask)"
    );
}

mod moma_set {
    use super::*;
    use image::RgbImage;

    fn make(root: &Path) -> MomaSetWriter {
        MomaSetWriter::create(root, &Intrinsics::nominal(ImageSize::new(4, 3))).unwrap()
    }

    #[test]
    fn missing_camera_json() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("frames/0")).unwrap();
        let e = MomaSet::open(dir.path()).unwrap_err();
        assert!(
            msg(&e).contains("camera.json") && msg(&e).contains("missing"),
            "{e}"
        );
        let e = MomaSet::open(dir.path().join("absent")).unwrap_err();
        assert!(
            msg(&e).contains("absent") && msg(&e).contains("does not exist"),
            "{e}"
        );
    }

    #[test]
    fn empty_frames_dir() {
        let dir = tempfile::tempdir().unwrap();
        make(dir.path());
        let e = MomaSet::open(dir.path()).unwrap_err();
        assert!(
            msg(&e).contains("no frames") && msg(&e).contains("frames"),
            "{e}"
        );
        std::fs::remove_dir(dir.path().join("frames")).unwrap();
        let e = MomaSet::open(dir.path()).unwrap_err();
        assert!(msg(&e).contains("frames/"), "{e}");
    }

    #[test]
    fn frame_without_depth() {
        let dir = tempfile::tempdir().unwrap();
        make(dir.path());
        let f = dir.path().join("frames/frame_7");
        std::fs::create_dir(&f).unwrap();
        write_rgb(f.join("rgb.png"), &RgbImage::new(4, 3)).unwrap();
        let e = MomaSet::open(dir.path()).unwrap_err();
        let m = msg(&e);
        assert!(m.contains("frame_7") && m.contains("depth.png"), "{m}");
    }

    #[test]
    fn frame_image_of_wrong_size() {
        let dir = tempfile::tempdir().unwrap();
        let w = make(dir.path());
        // The writer refuses mismatched sizes...
        let rgb = RgbImage::new(4, 3);
        let small = MetricDepth::new(Array2::ones((2, 2)));
        let e = w
            .write_frame(
                "x",
                FrameData {
                    rgb: &rgb,
                    depth: &small,
                    mask: None,
                    raw_depth: None,
                },
            )
            .unwrap_err();
        assert!(
            matches!(e, IoError::SizeMismatch { .. }) && msg(&e).contains("depth.png"),
            "{e}"
        );
        assert!(!dir.path().join("frames/x").exists());
        let e = w
            .write_frame(
                "../evil",
                FrameData {
                    rgb: &rgb,
                    depth: &small,
                    mask: None,
                    raw_depth: None,
                },
            )
            .unwrap_err();
        assert!(msg(&e).contains("invalid frame id"), "{e}");
        // ...and the loaders catch files that do not match camera.json.
        let good = MetricDepth::new(Array2::ones((3, 4)));
        w.write_frame(
            "x",
            FrameData {
                rgb: &rgb,
                depth: &good,
                mask: None,
                raw_depth: None,
            },
        )
        .unwrap();
        write_mask(
            dir.path().join("frames/x/mask.png"),
            &Mask::full(ImageSize::new(5, 5)),
        )
        .unwrap();
        let set = MomaSet::open(dir.path()).unwrap();
        let e = set.frames[0].load_mask().unwrap_err();
        assert!(
            matches!(e, IoError::SizeMismatch { .. }) && msg(&e).contains("mask.png"),
            "{e}"
        );
        assert!(set.frames[0].load_depth().is_ok());
    }
}

#[test]
fn colormap_range_errors() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("v.png");
    let d = MetricDepth::new(array![[1.0f32, 2.0]]);
    let e = write_depth_colormap(
        &p,
        &d,
        Colormap::Turbo,
        DepthRange::Fixed {
            min_m: 2.0,
            max_m: 1.0,
        },
    )
    .unwrap_err();
    assert!(
        msg(&e).contains("v.png") && msg(&e).contains("min < max"),
        "{e}"
    );
    assert!(!p.exists());
    assert!("jet".parse::<Colormap>().is_err());
}

#[test]
fn ply_colour_image_mismatch() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("c.ply");
    let k = Intrinsics::nominal(ImageSize::new(4, 3));
    let d = MetricDepth::new(Array2::ones((3, 4)));
    let e = write_depth_ply(
        &p,
        &d,
        &k,
        Some(&image::RgbImage::new(2, 2)),
        PlyFormat::Ascii,
    )
    .unwrap_err();
    assert!(
        msg(&e).contains("c.ply") && msg(&e).contains("colour image"),
        "{e}"
    );
    let e = write_depth_ply(
        &p,
        &MetricDepth::new(Array2::ones((2, 2))),
        &k,
        None,
        PlyFormat::Ascii,
    )
    .unwrap_err();
    assert!(matches!(e, IoError::Core { .. }), "{e}");
    assert!(!p.exists());
}

// ---------------------------------------------------------------------------------------------
// Resource limits: headers claiming huge images are refused before allocation
// ---------------------------------------------------------------------------------------------

/// CRC-32 (ISO-HDLC, as PNG uses), bit by bit.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A PNG signature and a well-formed `IHDR` chunk (16-bit grayscale), then `tail`.
fn png_header(width: u32, height: u32, tail: &[u8]) -> Vec<u8> {
    let mut chunk = b"IHDR".to_vec();
    chunk.extend_from_slice(&width.to_be_bytes());
    chunk.extend_from_slice(&height.to_be_bytes());
    chunk.extend_from_slice(&[16, 0, 0, 0, 0]); // bit depth, grayscale, deflate, filter, no interlace
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    out.extend_from_slice(&13u32.to_be_bytes());
    out.extend_from_slice(&chunk);
    out.extend_from_slice(&crc32(&chunk).to_be_bytes());
    out.extend_from_slice(tail);
    out
}

#[test]
fn crc32_matches_the_published_check_value() {
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
}

#[test]
fn png_header_claiming_100000_squared_is_too_large() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("huge.png");
    std::fs::write(&p, png_header(100_000, 100_000, &[])).unwrap();
    for e in [
        read_depth(&p).unwrap_err(),
        read_png16(&p).unwrap_err(),
        read_mask(&p).unwrap_err(),
        read_rgb(&p).unwrap_err(),
    ] {
        let m = msg(&e);
        assert!(
            matches!(
                e,
                IoError::TooLarge {
                    width: 100_000,
                    height: 100_000,
                    ..
                }
            ) && m.contains("huge.png")
                && m.contains("100000x100000")
                && m.contains("65535 pixels per side"),
            "{m}"
        );
    }
    // Within the side limit but over the pixel limit.
    std::fs::write(&p, png_header(60_000, 60_000, &[])).unwrap();
    let e = read_png16(&p).unwrap_err();
    assert!(
        matches!(e, IoError::TooLarge { .. }) && msg(&e).contains("67108864 pixels"),
        "{e}"
    );
}

#[test]
fn png_header_claiming_more_than_the_file_can_hold_is_corrupt() {
    // 8000×8000 16-bit is within the limits but needs 128 MB of pixel data: at deflate's best
    // ratio (1032:1) at least 124 032 bytes of file, and the file has 33 + 4.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("short.png");
    std::fs::write(&p, png_header(8000, 8000, b"\0\0\0\0")).unwrap();
    let e = read_png16(&p).unwrap_err();
    let m = msg(&e);
    assert!(
        matches!(e, IoError::Corrupt { .. })
            && m.contains("short.png")
            && m.contains("8000x8000")
            && m.contains("128000000 bytes")
            && m.contains("at least 124032")
            && m.contains("only 37"),
        "{m}"
    );
}

/// An npy v1.0 file: header dictionary padded to a multiple of 64 bytes, then `data`.
fn npy_bytes(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + dict.len() + 1) % 64 != 0 {
        dict.push(' ');
    }
    dict.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out.extend_from_slice(data);
    out
}

#[test]
fn npy_header_claiming_100000_squared_is_too_large() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("huge.npy");
    for shape in ["(100000, 100000)", "(1, 100000, 100000)"] {
        std::fs::write(&p, npy_bytes("<f4", shape, &[0; 16])).unwrap();
        for e in [
            read_depth(&p).unwrap_err(),
            read_npy_f32(&p).unwrap_err(),
            read_prediction(&p, PredictionKind::MetricDepth).unwrap_err(),
        ] {
            let m = msg(&e);
            assert!(
                matches!(
                    e,
                    IoError::TooLarge {
                        width: 100_000,
                        height: 100_000,
                        ..
                    }
                ) && m.contains("huge.npy")
                    && m.contains("npy header claims 100000x100000"),
                "{m}"
            );
        }
    }
    // A product that overflows 64 bits is refused too (not wrapped around).
    let shape = "(4294967296, 4294967296, 4294967296)";
    std::fs::write(&p, npy_bytes("<f4", shape, &[])).unwrap();
    assert!(matches!(
        read_npy_f32(&p).unwrap_err(),
        IoError::TooLarge { .. }
    ));
    // and the message states the shape (a saturated product divided by the height said
    // "3x4611686018427387904" for this one)
    std::fs::write(&p, npy_bytes("<f4", "(4611686018427387904, 4)", &[])).unwrap();
    let m = msg(&read_npy_f32(&p).unwrap_err());
    assert!(m.contains("claims 4x4611686018427387904"), "{m}");
}

#[test]
fn npy_data_length_must_match_the_header() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("len.npy");
    // 2×3 float64 needs 48 bytes.
    std::fs::write(&p, npy_bytes("<f8", "(2, 3)", &[0; 40])).unwrap();
    let m = msg(&read_npy_f32(&p).unwrap_err());
    assert!(
        m.contains("len.npy")
            && m.contains("needs 48 data bytes, the file has 40")
            && m.contains("truncated"),
        "{m}"
    );
    std::fs::write(&p, npy_bytes("<f8", "(2, 3)", &[0; 56])).unwrap();
    let m = msg(&read_npy_f32(&p).unwrap_err());
    assert!(m.contains("needs 48 data bytes, the file has 56"), "{m}");
    // Exactly right: reads.
    std::fs::write(&p, npy_bytes("<f8", "(2, 3)", &[0; 48])).unwrap();
    assert_eq!(read_npy_f32(&p).unwrap(), Array2::<f32>::zeros((2, 3)));
}

#[test]
fn pfm_header_claiming_100000_squared_is_too_large() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("huge.pfm");
    std::fs::write(&p, b"Pf\n100000 100000\n-1.0\n\0\0\0\0").unwrap();
    let e = read_depth(&p).unwrap_err();
    let m = msg(&e);
    assert!(
        matches!(
            e,
            IoError::TooLarge {
                width: 100_000,
                height: 100_000,
                ..
            }
        ) && m.contains("huge.pfm")
            && m.contains("PFM header claims 100000x100000"),
        "{m}"
    );
}

#[test]
fn npy_header_length_beyond_the_file_is_refused_before_allocation() {
    // Found by moma-fuzz (npy target, seed 0, iteration 17129): a version-3 npy header whose
    // 32-bit length field claims 3 GB in a 187-byte file made ndarray-npy allocate 3 GB for the
    // header before reading it.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("long_header.npy");
    let mut b = b"\x93NUMPY\x03\x00".to_vec();
    b.extend_from_slice(&0xb400_12b6u32.to_le_bytes());
    b.extend_from_slice(b"{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2), }\n");
    b.extend_from_slice(&[0; 16]);
    std::fs::write(&p, &b).unwrap();
    let e = read_npy_f32(&p).unwrap_err();
    let m = msg(&e);
    assert!(
        matches!(e, IoError::Corrupt { .. })
            && m.contains("long_header.npy")
            && m.contains("header claims 3019903670 bytes")
            && m.contains(&format!("only {} follow", b.len() - 12)),
        "{m}"
    );
    // Version 1 (16-bit length) likewise.
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&0xfff0u16.to_le_bytes());
    b.extend_from_slice(b"{'descr': '<f4', 'shape': (1, 1), }\n");
    std::fs::write(&p, &b).unwrap();
    assert!(msg(&read_npy_f32(&p).unwrap_err()).contains("header claims 65520 bytes"));
}

/// An image given where a JSON file belongs is said to be binary, naming the file and what was
/// expected (it was "cannot read: stream did not contain valid UTF-8").
#[test]
fn an_image_where_json_belongs_is_named_as_not_text() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("rgb.png");
    write_small_png(&png);
    let camera = moma_io::read_camera(&png).unwrap_err();
    let calibration = moma_io::read_calibration(&png).unwrap_err();
    for (e, what) in [
        (camera, "camera intrinsics (camera.json)"),
        (calibration, "calibration file"),
    ] {
        assert!(matches!(e, IoError::Invalid { .. }), "{e}");
        let m = msg(&e);
        assert!(
            m.contains("rgb.png") && m.contains(what) && m.contains("not a JSON text file"),
            "{m}"
        );
    }
}

/// Every writer refuses a map that its readers would refuse (over 65 535 pixels per side), with
/// nothing left at the path: a file is not written that cannot be read back.
#[test]
fn a_map_no_reader_accepts_is_not_written() {
    let dir = tempfile::tempdir().unwrap();
    let wide = MetricDepth::new(Array2::from_elem((1, 70_000), 0.7f32));
    for name in ["wide.npy", "wide.pfm", "wide.png"] {
        let path = dir.path().join(name);
        let e = write_depth(&path, &wide).unwrap_err();
        assert!(
            msg(&e).contains("cannot write a 70000x1 map")
                && msg(&e).contains("65535 pixels per side"),
            "{name}: {e}"
        );
        assert!(!path.exists(), "{name}");
    }
    // the widest readable map round-trips
    let edge = MetricDepth::new(Array2::from_elem((1, 65_535), 0.7f32));
    let path = dir.path().join("edge.npy");
    write_depth(&path, &edge).unwrap();
    assert_eq!(read_depth(&path).unwrap().size(), edge.size());
}
