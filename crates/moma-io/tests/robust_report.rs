//! A calibration fitted with a robust fit keeps its report (kind, threshold, inliers,
//! iterations) through the calibration file; a file without it (every file written before robust
//! fits) still reads; an inconsistent report is refused naming the problem.

use moma_core::CalibrationFrame;
use moma_core::align::Method;
use moma_core::align::robust::{Robust, RobustKind};
use moma_core::normalise::{AlignSpace, Normalisation, NormalisationConfig};
use moma_core::sampling::SamplingConfig;
use moma_core::{CalibrationConfig, MetricDepth, Prediction, PredictionKind, calibrate};
use moma_io::{CalibrationFile, CreationInfo, read_calibration, write_calibration};
use ndarray::Array2;

fn calibration(robust: Option<Robust>) -> moma_core::pipeline::Calibration {
    let gt = MetricDepth::new(Array2::from_shape_fn((24, 32), |(v, u)| {
        let z = 0.6 + 0.01 * v as f32;
        if (u + v).is_multiple_of(5) {
            z + 0.2
        } else {
            z
        }
    }));
    let pred = Prediction::new(
        Array2::from_shape_fn((24, 32), |(v, _)| 1.0 / (0.6 + 0.01 * v as f32)),
        PredictionKind::RelativeDisparity,
    );
    let config = CalibrationConfig {
        method: Method::Gssa,
        normalisation: NormalisationConfig {
            method: Normalisation::None,
            space: AlignSpace::Inverse,
        },
        sampling: SamplingConfig {
            n: 60,
            seed: 2,
            ..Default::default()
        },
        robust,
        workspace: None,
    };
    calibrate(&[CalibrationFrame::new(&pred, &gt)], &config).unwrap()
}

#[test]
fn robust_report_round_trips_and_is_checked() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("calib.json");
    let cal = calibration(Some(Robust::new(RobustKind::Ransac)));
    let rep = cal.report.robust.unwrap();
    let outliers = cal
        .samples
        .samples
        .iter()
        .filter(|s| (s.u as usize + s.v as usize).is_multiple_of(5))
        .count();
    assert_eq!(rep.inliers, cal.samples.len() - outliers);
    // the default threshold is `auto`: the report records the scale (exact data: the floor)
    let auto = rep.auto.unwrap();
    assert_eq!(auto.scale_m, moma_core::align::robust::SCALE_FLOOR_M);
    let file = CalibrationFile::new(cal, None, CreationInfo::now());
    write_calibration(&path, &file).unwrap();
    let back = read_calibration(&path).unwrap();
    assert_eq!(back.calibration, file.calibration);

    // an inconsistent report: more inliers than samples
    let text = std::fs::read_to_string(&path).unwrap();
    let needle = format!("\"inliers\": {}", rep.inliers);
    assert!(text.contains(&needle), "{text}");
    std::fs::write(&path, text.replace(&needle, "\"inliers\": 1000")).unwrap();
    let err = read_calibration(&path).unwrap_err();
    let mut chain = err.to_string();
    let mut source = std::error::Error::source(&err);
    while let Some(e) = source {
        chain.push_str(&format!(": {e}"));
        source = e.source();
    }
    assert!(chain.contains("1000 inliers"), "{chain}");

    // a report without the `auto` block (a fixed threshold, or a version-3 file written before
    // the block existed) reads back; a bad scale is refused naming the field
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("\"inliers\": 1000", &needle);
    let key = text.find("\"auto\"").unwrap();
    let start = text[..key].rfind(',').unwrap();
    let end = key + text[key..].find('}').unwrap() + 1;
    let mut without = text.clone();
    without.replace_range(start..end, "");
    assert!(!without.contains("scale_m"), "{without}");
    std::fs::write(&path, &without).unwrap();
    assert_eq!(
        read_calibration(&path)
            .unwrap()
            .calibration
            .report
            .robust
            .unwrap()
            .auto,
        None
    );
    let scale = format!("\"scale_m\": {}", auto.scale_m);
    assert!(text.contains(&scale), "{text}");
    std::fs::write(&path, text.replace(&scale, "\"scale_m\": -1.0")).unwrap();
    let err = read_calibration(&path).unwrap_err();
    let mut chain = err.to_string();
    let mut source = std::error::Error::source(&err);
    while let Some(e) = source {
        chain.push_str(&format!(": {e}"));
        source = e.source();
    }
    assert!(chain.contains("auto.scale_m"), "{chain}");

    // a plain fit writes no robust block and reads back
    let plain = CalibrationFile::new(calibration(None), None, CreationInfo::now());
    write_calibration(&path, &plain).unwrap();
    assert!(
        !std::fs::read_to_string(&path)
            .unwrap()
            .contains("\"robust\"")
    );
    assert_eq!(
        read_calibration(&path).unwrap().calibration.report.robust,
        None
    );
}
