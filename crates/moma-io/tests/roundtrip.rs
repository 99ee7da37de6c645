//! Round trips of every format moma-io writes, with independent checks of the bytes on disk.

use image::{Rgb, RgbImage};
use moma_core::align::{AlignmentModel, FitReport, Sample, SampleSet};
use moma_core::normalise::{Normalisation, NormalisationConfig};
use moma_core::pipeline::Calibration;
use moma_core::{ImageSize, Intrinsics, Mask, MetricDepth, Prediction, PredictionKind};
use moma_io::*;
use ndarray::{Array2, Array3, array};
use proptest::prelude::*;

fn ramp(h: usize, w: usize) -> Array2<f32> {
    Array2::from_shape_fn((h, w), |(v, u)| 0.25 + 0.001 * (v * w + u) as f32)
}

#[test]
fn png16_depth_is_exact_in_millimetres() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("d.png");
    let mm = Array2::from_shape_fn((5, 7), |(v, u)| (v * 7 + u) as u16 * 997 % 65535);
    let depth = MetricDepth::new(mm.mapv(|m| if m == 0 { f32::NAN } else { m as f32 / 1000.0 }));
    let stats = write_depth(&p, &depth).unwrap();
    assert_eq!(stats.pixels, 35);
    assert_eq!(stats.invalid, 1);
    assert_eq!(stats.out_of_range, 0);
    // The raw file holds exactly the millimetres.
    assert_eq!(read_png16(&p).unwrap(), mm);
    let back = read_depth(&p).unwrap();
    for (a, b) in back.depth_m.iter().zip(depth.depth_m.iter()) {
        assert!((a.is_nan() && b.is_nan()) || a == b, "{a} vs {b}");
    }
    // Independent decoder: the image crate sees a 16-bit grayscale PNG.
    let img = image::open(&p).unwrap();
    assert_eq!(img.color(), image::ColorType::L16);
    assert_eq!(img.as_luma16().unwrap().get_pixel(3, 2).0[0], mm[[2, 3]]);
}

#[test]
fn png16_depth_rounds_and_zeroes_unrepresentable() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("d.png");
    let depth = MetricDepth::new(array![[
        1.0004f32,
        1.0006,
        70.0,
        -0.5,
        f32::INFINITY,
        0.0001
    ]]);
    let stats = write_depth(&p, &depth).unwrap();
    assert_eq!((stats.invalid, stats.out_of_range), (2, 2));
    assert_eq!(read_png16(&p).unwrap(), array![[1000u16, 1001, 0, 0, 0, 0]]);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    #[test]
    fn png16_roundtrip_any_millimetres(mm in proptest::collection::vec(0u16..=65535, 12)) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.png");
        let depth = MetricDepth::new(Array2::from_shape_vec((3, 4), mm.iter().map(|&m| m as f32 / 1000.0).collect()).unwrap());
        write_depth(&p, &depth).unwrap();
        let raw = read_png16(&p).unwrap();
        prop_assert_eq!(raw.iter().copied().collect::<Vec<_>>(), mm);
    }
}

#[test]
fn npy_depth_is_exact_and_keeps_nan() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("d.npy");
    let mut z = ramp(4, 6);
    z[[1, 2]] = f32::NAN;
    z[[0, 0]] = 123.456_79;
    write_depth(&p, &MetricDepth::new(z.clone())).unwrap();
    let back = read_depth(&p).unwrap().depth_m;
    assert_eq!(back.dim(), (4, 6));
    for (a, b) in back.iter().zip(z.iter()) {
        assert!(a.to_bits() == b.to_bits(), "{a} vs {b}");
    }
    // Header written as NumPy expects: float32 little-endian, C order, shape (4, 6).
    let bytes = std::fs::read(&p).unwrap();
    assert_eq!(&bytes[..6], b"\x93NUMPY");
    let header = String::from_utf8_lossy(&bytes[10..80]);
    assert!(
        header.contains("'descr': '<f4'") && header.contains("(4, 6)"),
        "{header}"
    );
}

#[test]
fn npy_reads_f64_squeezes_and_fortran_order() {
    use ndarray_npy::write_npy;
    let dir = tempfile::tempdir().unwrap();
    let z64 = Array2::from_shape_fn((3, 5), |(v, u)| 0.5 + (v * 5 + u) as f64 * 0.125);
    let expect = z64.mapv(|v| v as f32);
    let p = dir.path().join("f64.npy");
    write_npy(&p, &z64).unwrap();
    assert_eq!(read_depth(&p).unwrap().depth_m, expect);

    let p = dir.path().join("chw.npy");
    write_npy(&p, &expect.clone().insert_axis(ndarray::Axis(0))).unwrap();
    assert_eq!(read_npy_f32(&p).unwrap(), expect);

    let p = dir.path().join("hwc.npy");
    write_npy(&p, &expect.clone().insert_axis(ndarray::Axis(2))).unwrap();
    assert_eq!(read_npy_f32(&p).unwrap(), expect);

    // A Fortran-ordered (column-major) file: the transpose view is F-contiguous.
    let p = dir.path().join("fortran.npy");
    let t = expect.t().as_standard_layout().into_owned(); // (5, 3), C order
    write_npy(&p, &t.t()).unwrap(); // stored as F-order (3, 5)
    let bytes = std::fs::read(&p).unwrap();
    let head = String::from_utf8_lossy(&bytes[..100]).to_string();
    assert!(head.contains("'fortran_order': True"), "{head}");
    assert_eq!(read_npy_f32(&p).unwrap(), expect);

    // Other 3-D shapes are refused with the shape in the message.
    let p = dir.path().join("rgb.npy");
    write_npy(&p, &Array3::<f32>::zeros((2, 3, 3))).unwrap();
    let e = read_npy_f32(&p).unwrap_err().to_string();
    assert!(e.contains("rgb.npy") && e.contains("[2, 3, 3]"), "{e}");
}

#[test]
fn pfm_roundtrip_both_byte_orders() {
    let dir = tempfile::tempdir().unwrap();
    let mut z = ramp(3, 4);
    z[[2, 3]] = f32::NAN;
    for (order, scale, name) in [
        (PfmByteOrder::LittleEndian, "-1.0", "le.pfm"),
        (PfmByteOrder::BigEndian, "1.0", "be.pfm"),
    ] {
        let p = dir.path().join(name);
        write_pfm(&p, z.view(), order).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let header = format!("Pf\n4 3\n{scale}\n");
        assert!(bytes.starts_with(header.as_bytes()));
        // First stored row is the image's bottom row (PFM is bottom-to-top).
        let first: [u8; 4] = bytes[header.len()..header.len() + 4].try_into().unwrap();
        let first = match order {
            PfmByteOrder::LittleEndian => f32::from_le_bytes(first),
            PfmByteOrder::BigEndian => f32::from_be_bytes(first),
        };
        assert_eq!(first, z[[2, 0]]);
        let back = read_pfm(&p).unwrap();
        for (a, b) in back.iter().zip(z.iter()) {
            assert!(a.to_bits() == b.to_bits());
        }
    }
    // Generic depth I/O uses little-endian.
    let p = dir.path().join("d.pfm");
    write_depth(&p, &MetricDepth::new(z.clone())).unwrap();
    assert!(std::fs::read(&p).unwrap().starts_with(b"Pf\n4 3\n-1.0\n"));
    assert_eq!(read_depth(&p).unwrap().depth_m[[1, 1]], z[[1, 1]]);
}

#[test]
fn predictions_keep_raw_values_and_kind() {
    let dir = tempfile::tempdir().unwrap();
    let pred = Prediction::new(
        array![[0.0f32, 3.5], [-1.0, 1e6]],
        PredictionKind::RelativeDisparity,
    );
    for name in ["p.npy", "p.pfm"] {
        let p = dir.path().join(name);
        write_prediction(&p, &pred).unwrap();
        let back = read_prediction(&p, PredictionKind::RelativeDisparity).unwrap();
        assert_eq!(back, pred);
    }
    // A 16-bit PNG prediction is read as raw values (no millimetre conversion).
    let p = dir.path().join("disp.png");
    write_depth(
        &p,
        &MetricDepth::new(array![[0.0f32, 0.007], [1.0, 65.535]]),
    )
    .unwrap();
    let back = read_prediction(&p, PredictionKind::MetricDepth).unwrap();
    assert_eq!(back.values, array![[0.0f32, 7.0], [1000.0, 65535.0]]);
    assert_eq!(back.kind, PredictionKind::MetricDepth);
}

#[test]
fn masks_roundtrip_and_convert() {
    let dir = tempfile::tempdir().unwrap();
    let m = Mask::new(Array2::from_shape_fn((4, 5), |(v, u)| (u + v) % 3 == 0));
    let p = dir.path().join("m.png");
    write_mask(&p, &m).unwrap();
    assert_eq!(read_mask(&p).unwrap(), m);
    let raw = image::open(&p).unwrap();
    assert_eq!(raw.color(), image::ColorType::L8);
    assert_eq!(raw.as_luma8().unwrap().get_pixel(0, 0).0[0], 255);
    assert_eq!(raw.as_luma8().unwrap().get_pixel(1, 0).0[0], 0);

    // 1-bit grayscale written with the png crate directly.
    let p1 = dir.path().join("m1.png");
    {
        let f = std::io::BufWriter::new(std::fs::File::create(&p1).unwrap());
        let mut enc = png::Encoder::new(f, 8, 2);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::One);
        let mut w = enc.write_header().unwrap();
        w.write_image_data(&[0b1010_0000, 0b0000_0001]).unwrap();
    }
    let m1 = read_mask(&p1).unwrap();
    assert_eq!(m1.size(), ImageSize::new(8, 2));
    assert_eq!(m1.count(), 3);
    assert!(m1.data()[[0, 0]] && !m1.data()[[0, 1]] && m1.data()[[0, 2]] && m1.data()[[1, 7]]);

    // 16-bit grayscale: nonzero = inside.
    let p16 = dir.path().join("m16.png");
    write_depth(&p16, &MetricDepth::new(array![[0.0f32, 0.001], [2.0, 0.0]])).unwrap();
    assert_eq!(
        read_mask(&p16).unwrap().data(),
        &array![[false, true], [true, false]]
    );

    // RGB: any colour channel nonzero = inside.
    let prgb = dir.path().join("mrgb.png");
    let img = RgbImage::from_fn(3, 1, |x, _| {
        Rgb([0, if x == 1 { 9 } else { 0 }, if x == 2 { 1 } else { 0 }])
    });
    write_rgb(&prgb, &img).unwrap();
    assert_eq!(
        read_mask(&prgb).unwrap().data(),
        &array![[false, true, true]]
    );

    // Size-checked loader.
    assert!(read_mask_sized(&p, ImageSize::new(5, 4)).is_ok());
}

/// An instance label image, as segmentation tools write one (a grey level or a colour per
/// object), in an 8-bit, a 16-bit and an RGB PNG: two 20 × 20 objects that touch along a
/// column read as objects to grasp as two 8-connected components, each without its seam
/// column; the same objects in one value (a 0/255 mask) read as one; as a mask (`read_mask`)
/// every non-zero pixel is inside.
#[test]
fn instance_label_masks_keep_touching_objects_apart() {
    let dir = tempfile::tempdir().unwrap();
    let which = |v: u32, u: u32| match (v, u) {
        (10..30, 10..30) => 1,
        (10..30, 30..50) => 2,
        _ => 0,
    };
    let components = |m: &Mask| {
        let flat: Vec<bool> = m.data().iter().copied().collect();
        moma_core::image::components_8(&flat, m.size()).1
    };
    let grey = |levels: [u8; 3]| {
        image::GrayImage::from_fn(60, 40, |u, v| image::Luma([levels[which(v, u)]]))
    };
    let p8 = dir.path().join("labels8.png");
    grey([0, 100, 200]).save(&p8).unwrap();
    let p16 = dir.path().join("labels16.png");
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(60, 40, |u, v| {
        image::Luma([[0u16, 1, 2][which(v, u)]])
    })
    .save(&p16)
    .unwrap();
    let prgb = dir.path().join("labels_rgb.png");
    let colours = [[0u8, 0, 0], [255, 0, 0], [0, 0, 255]];
    RgbImage::from_fn(60, 40, |u, v| Rgb(colours[which(v, u)]))
        .save(&prgb)
        .unwrap();
    let size = ImageSize::new(60, 40);
    for p in [&p8, &p16, &prgb] {
        let m = read_object_mask_sized(p, size).unwrap();
        assert_eq!(components(&m), [380, 380], "{}", p.display());
        assert!(!m.data()[[20, 29]] && !m.data()[[20, 30]] && m.data()[[20, 28]]);
        // as an evaluation region or a sample mask, every non-zero pixel
        assert_eq!(components(&read_mask(p).unwrap()), [800], "{}", p.display());
    }
    let pbin = dir.path().join("binary.png");
    grey([0, 255, 255]).save(&pbin).unwrap();
    assert_eq!(
        components(&read_object_mask_sized(&pbin, size).unwrap()),
        [800]
    );
    assert!(read_object_mask_sized(&pbin, ImageSize::new(61, 40)).is_err());
}

#[test]
fn rgb_png_exact_and_jpeg_close() {
    let dir = tempfile::tempdir().unwrap();
    let img = RgbImage::from_fn(16, 8, |x, y| Rgb([(x * 16) as u8, (y * 32) as u8, 128]));
    let p = dir.path().join("c.png");
    write_rgb(&p, &img).unwrap();
    assert_eq!(read_rgb(&p).unwrap(), img);
    assert_eq!(read_rgb_sized(&p, ImageSize::new(16, 8)).unwrap(), img);
    let pj = dir.path().join("c.JPG");
    write_rgb(&pj, &img).unwrap();
    let back = read_rgb(&pj).unwrap();
    assert_eq!(back.dimensions(), (16, 8));
    let max_err = img
        .as_raw()
        .iter()
        .zip(back.as_raw())
        .map(|(&a, &b)| (a as i16 - b as i16).abs())
        .max()
        .unwrap();
    assert!(max_err < 40, "JPEG error {max_err}");
    // Content decides, not the extension: a PNG named .jpg still reads.
    let mislabelled = dir.path().join("really_png.jpg");
    std::fs::copy(&p, &mislabelled).unwrap();
    assert_eq!(read_rgb(&mislabelled).unwrap(), img);
}

#[test]
fn camera_json_roundtrip() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("camera.json");
    let k = Intrinsics {
        width: 640,
        height: 480,
        fx: 616.365_295_410_156_2,
        fy: 616.2,
        cx: 310.25,
        cy: 236.5,
    };
    write_camera(&p, &k).unwrap();
    assert_eq!(read_camera(&p).unwrap(), k);
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    assert_eq!(v["width"], 640);
    assert_eq!(v["fx"], 616.365_295_410_156_2);
    // Extra fields are ignored.
    std::fs::write(
        &p,
        r#"{"width":2,"height":1,"fx":1,"fy":1,"cx":0.5,"cy":0,"depth_scale":1000}"#,
    )
    .unwrap();
    assert_eq!(read_camera(&p).unwrap().size(), ImageSize::new(2, 1));
}

pub fn sample_calibration() -> Calibration {
    Calibration {
        normalisation: NormalisationConfig {
            method: Normalisation::Median,
            space: moma_core::AlignSpace::Inverse,
        },
        prediction_kind: PredictionKind::RelativeDisparity,
        model: AlignmentModel::Gssa(moma_core::align::gssa::GssaModel {
            scale: 0.25,
            shift: 0.5,
        }),
        report: FitReport {
            method: moma_core::align::MethodName::Gssa,
            n_used: 2,
            rms_residual_m: 0.012_345_678_9,
            fit_time_s: 1.5e-6,
            robust: None,
        },
        samples: SampleSet {
            space: moma_core::normalise::AlignSpace::Depth,
            image_size: ImageSize::new(64, 48),
            samples: vec![
                Sample {
                    u: 1.0,
                    v: 2.0,
                    pred: 0.3,
                    target: 0.812,
                },
                Sample {
                    u: 60.0,
                    v: 40.0,
                    pred: -1.25,
                    target: 1.1,
                },
            ],
        },
        workspace: None,
        anchors: None,
        error_model: None,
        normalisation_notes: Vec::new(),
    }
}

#[test]
fn calibration_file_roundtrip() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("calib.json");
    let created = CreationInfo {
        moma_version: "0.1.0".into(),
        created_unix_s: 1_700_000_000,
        command_line: vec!["moma".into(), "calibrate".into()],
        sources: Default::default(),
        simulated_predictions: true,
    }
    .with_source("prediction", "frames/a/pred.npy");
    let k = Intrinsics::nominal(ImageSize::new(64, 48));
    let mut cal = sample_calibration();
    let ws = moma_core::Mask::new(ndarray::Array2::from_shape_fn((48, 64), |(v, u)| {
        u > 3 && v < 40
    }));
    cal.workspace = Some(std::sync::Arc::new(moma_core::Workspace::new(ws).unwrap()));
    let file = CalibrationFile::new(cal, Some(k), created);
    write_calibration(&p, &file).unwrap();
    let back = read_calibration(&p).unwrap();
    assert_eq!(back, file);
    // The documented top-level fields are there for scripts.
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    assert_eq!(v["format"], "moma-calibration");
    assert_eq!(v["version"], 9);
    assert_eq!(v["method"], "gssa");
    assert_eq!(v["normalisation"]["space"], "inverse");
    assert_eq!(v["calibration"]["workspace"]["inside_px"], 60 * 40);
    // copied to another folder, the file still holds its workspace
    let elsewhere = tempfile::tempdir().unwrap();
    let q = elsewhere.path().join("moved.json");
    std::fs::copy(&p, &q).unwrap();
    drop(dir);
    assert_eq!(read_calibration(&q).unwrap(), file);
    assert_eq!(v["prediction_kind"], "relative-disparity");
    assert_eq!(v["normalisation"]["method"], "median");
    assert_eq!(v["image_size"]["width"], 64);
    assert_eq!(v["created"]["sources"]["prediction"], "frames/a/pred.npy");
    // CreationInfo::now fills the version and a plausible time.
    let now = CreationInfo::now();
    assert_eq!(now.moma_version, env!("CARGO_PKG_VERSION"));
    assert!(now.created_unix_s > 1_600_000_000);
}

#[test]
fn colormap_png_records_its_range() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("vis.png");
    let mut z = ramp(10, 20);
    z[[0, 0]] = f32::NAN;
    z[[0, 1]] = 0.0;
    z[[9, 19]] = 1.0;
    let depth = MetricDepth::new(z);
    let scale = write_depth_colormap(
        &p,
        &depth,
        Colormap::Viridis,
        DepthRange::Fixed {
            min_m: 0.25,
            max_m: 0.45,
        },
    )
    .unwrap();
    assert_eq!(
        scale,
        ColourScale {
            colormap: Colormap::Viridis,
            min_m: 0.25,
            max_m: 0.45
        }
    );
    assert_eq!(read_colour_scale(&p).unwrap(), Some(scale));
    let img = read_rgb(&p).unwrap();
    assert_eq!(img.get_pixel(0, 0).0, [0, 0, 0]);
    assert_eq!(img.get_pixel(1, 0).0, [0, 0, 0]);
    assert_eq!(img.get_pixel(19, 9).0, Colormap::Viridis.rgb(1.0));
    // Automatic range: within the valid values.
    let p2 = dir.path().join("auto.png");
    let s2 = write_depth_colormap(&p2, &depth, Colormap::Turbo, DepthRange::default()).unwrap();
    assert!(
        s2.min_m > 0.25 && s2.max_m < 0.45 && s2.min_m < s2.max_m,
        "{s2:?}"
    );
    assert_eq!(read_colour_scale(&p2).unwrap(), Some(s2));
    // A σ map: the same range chunks, described as what it is (tEXt is stored uncompressed)
    let p4 = dir.path().join("sigma.png");
    let s4 = write_sigma_colormap(&p4, &depth, Colormap::Turbo, DepthRange::default()).unwrap();
    assert_eq!(s4, s2);
    assert_eq!(read_colour_scale(&p4).unwrap(), Some(s4));
    let has = |p: &std::path::Path, text: &str| {
        let bytes = std::fs::read(p).unwrap();
        bytes.windows(text.len()).any(|w| w == text.as_bytes())
    };
    assert!(has(&p4, "moma sigma (1 SD) of the depth error, colour map"));
    assert!(!has(&p4, "moma depth,"));
    assert!(has(&p2, "moma depth, colour map"));
    // A PNG without the chunks has no scale.
    let p3 = dir.path().join("plain.png");
    write_rgb(&p3, &colour_bar(Colormap::Turbo, 32, 4)).unwrap();
    assert_eq!(read_colour_scale(&p3).unwrap(), None);
}

/// Minimal independent PLY reader for the tests: header lines and the body bytes.
fn split_ply(bytes: &[u8]) -> (Vec<String>, &[u8]) {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    let header = String::from_utf8(bytes[..end].to_vec()).unwrap();
    (header.lines().map(str::to_string).collect(), &bytes[end..])
}

#[test]
fn ply_binary_parses_back() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("cloud.ply");
    let k = Intrinsics {
        width: 4,
        height: 3,
        fx: 2.0,
        fy: 4.0,
        cx: 1.5,
        cy: 1.0,
    };
    let mut z = Array2::from_elem((3, 4), 2.0f32);
    z[[0, 0]] = f32::NAN;
    z[[2, 3]] = 0.0;
    let rgb = RgbImage::from_fn(4, 3, |x, y| Rgb([x as u8 * 10, y as u8 * 20, 7]));
    let n = write_depth_ply(
        &p,
        &MetricDepth::new(z),
        &k,
        Some(&rgb),
        PlyFormat::BinaryLittleEndian,
    )
    .unwrap();
    assert_eq!(n, 10);
    let bytes = std::fs::read(&p).unwrap();
    let (header, body) = split_ply(&bytes);
    assert_eq!(header[0], "ply");
    assert_eq!(header[1], "format binary_little_endian 1.0");
    assert!(header.iter().any(|l| l == "comment units: metres"));
    assert!(
        header
            .iter()
            .any(|l| l.starts_with("comment frame: camera"))
    );
    assert!(header.iter().any(|l| l == "element vertex 10"));
    let props: Vec<&String> = header
        .iter()
        .filter(|l| l.starts_with("property"))
        .collect();
    assert_eq!(
        props,
        [
            "property float x",
            "property float y",
            "property float z",
            "property uchar red",
            "property uchar green",
            "property uchar blue"
        ]
    );
    assert_eq!(body.len(), 10 * 15);
    let vertex = |i: usize| {
        let r = &body[i * 15..(i + 1) * 15];
        let f = |o: usize| f32::from_le_bytes(r[o..o + 4].try_into().unwrap());
        ([f(0), f(4), f(8)], [r[12], r[13], r[14]])
    };
    // First valid pixel is (u=1, v=0): x = (1 - 1.5)·2/2, y = (0 - 1)·2/4.
    assert_eq!(vertex(0), ([-0.5, -0.5, 2.0], [10, 0, 7]));
    // Last valid pixel is (u=2, v=2).
    assert_eq!(vertex(9), ([0.5, 0.5, 2.0], [20, 40, 7]));
}

#[test]
fn ply_ascii_without_colour() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("cloud.ply");
    let pts = [
        moma_core::CameraPoint {
            xyz_m: [0.1, -0.2, 1.5],
            u: 0,
            v: 0,
        },
        moma_core::CameraPoint {
            xyz_m: [1e-3, 2.0, 0.75],
            u: 1,
            v: 0,
        },
    ];
    assert_eq!(write_ply(&p, &pts, None, PlyFormat::Ascii).unwrap(), 2);
    let text = std::fs::read_to_string(&p).unwrap();
    let (header, body) = split_ply(text.as_bytes());
    assert_eq!(header[1], "format ascii 1.0");
    assert!(!header.iter().any(|l| l.contains("uchar")));
    let rows: Vec<Vec<f32>> = std::str::from_utf8(body)
        .unwrap()
        .lines()
        .map(|l| l.split(' ').map(|t| t.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows, vec![vec![0.1, -0.2, 1.5], vec![1e-3, 2.0, 0.75]]);
}

#[test]
fn moma_set_writer_then_open() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("demo");
    let k = Intrinsics::nominal(ImageSize::new(6, 4));
    let w = MomaSetWriter::create(&root, &k).unwrap();
    w.write_readme("# demo\nsimulated\n").unwrap();
    let rgb = RgbImage::from_pixel(6, 4, Rgb([1, 2, 3]));
    let depth = MetricDepth::new(ramp(4, 6));
    let mask = Mask::new(Array2::from_shape_fn((4, 6), |(v, _)| v > 1));
    for id in ["b", "a", "c10", "c2"] {
        let data = FrameData {
            rgb: &rgb,
            depth: &depth,
            mask: (id != "a").then_some(&mask),
            raw_depth: (id == "b").then_some(&depth),
        };
        let stats = w.write_frame(id, data).unwrap();
        assert_eq!(stats.out_of_range, 0);
    }
    // Stray files are ignored by open.
    std::fs::write(root.join("frames").join("notes.txt"), "x").unwrap();
    let set = MomaSet::open(&root).unwrap();
    assert_eq!(set.camera, k);
    assert_eq!(set.name(), "demo");
    let ids: Vec<&str> = set.frames.iter().map(|f| f.id.as_str()).collect();
    assert_eq!(ids, ["a", "b", "c10", "c2"]);
    let a = set.frame("a").unwrap();
    assert!(a.mask.is_none() && a.raw_depth.is_none());
    assert_eq!(a.load_mask_or_full().unwrap().count(), 24);
    let b = set.frame("b").unwrap();
    assert_eq!(b.load_rgb().unwrap(), rgb);
    assert_eq!(b.load_mask().unwrap().unwrap(), mask);
    let d = b.load_depth().unwrap().depth_m;
    assert!(
        d.iter()
            .zip(depth.depth_m.iter())
            .all(|(x, y)| (x - y).abs() < 0.0005 + 1e-6)
    );
    assert!(b.load_raw_depth().unwrap().is_some());
    assert_eq!(b.file("pred.npy"), root.join("frames/b/pred.npy"));
}

/// `aligned.json` records the paths it names absolute, made so against the working directory.
#[test]
fn the_aligned_index_records_absolute_paths() {
    let cwd = std::env::current_dir().unwrap();
    let relative = std::path::Path::new("cell").join("calib.json");
    // made absolute against the working directory, the file need not exist, links not resolved
    assert_eq!(
        recorded_path(&relative),
        cwd.join("cell").join("calib.json").display().to_string()
    );
    let absolute = std::env::temp_dir().join("x.npy");
    assert_eq!(recorded_path(&absolute), absolute.display().to_string());
}

/// `aligned.json` (the provenance index of aligned depth): written, merged by file name, read
/// back for the listed files only; another tool's file of that name says nothing (and is never
/// overwritten); a corrupt or newer one of moma's is an error.
#[test]
fn the_aligned_index_records_merges_and_refuses_what_is_not_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let entry = |file: &str, simulated: bool| AlignedFile {
        file: file.into(),
        simulated,
        written_by: "moma align".into(),
        calibration: Some("calib.json".into()),
        method: Some("ssra".into()),
        input: Some(format!("preds/{file}")),
    };
    assert_eq!(read_aligned_index(dir.path()).unwrap(), None);
    let of = |file: &str| provenance_of(&dir.path().join(file)).unwrap();
    assert_eq!(of("a.depth.npy"), Provenance::Unlisted);
    record_aligned_files(
        dir.path(),
        vec![entry("a.depth.npy", true), entry("b.v2.depth.png", true)],
    )
    .unwrap();
    record_aligned_files(
        dir.path(),
        vec![entry("a.depth.npy", false), entry("depth.npy", true)],
    )
    .unwrap();
    let on_disk: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join(ALIGNED_INDEX_FILE)).unwrap(),
    )
    .unwrap();
    assert_eq!(on_disk["format"], "moma-aligned");
    assert_eq!(on_disk["version"], 1);
    let files: Vec<&str> = on_disk["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["file"].as_str().unwrap())
        .collect();
    assert_eq!(files, ["a.depth.npy", "b.v2.depth.png", "depth.npy"]);
    let simulated = |file: &str| match of(file) {
        Provenance::Listed { entry, index } => {
            assert_eq!(index, dir.path().join(ALIGNED_INDEX_FILE));
            Some(entry.simulated)
        }
        _ => None,
    };
    assert_eq!(simulated("a.depth.npy"), Some(false));
    assert_eq!(simulated("b.v2.depth.png"), Some(true));
    assert_eq!(simulated("depth.npy"), Some(true));
    for unlisted in ["a.sigma.npy", "b.depth.npy", "xa.depth.npy"] {
        assert_eq!(of(unlisted), Provenance::Unlisted, "{unlisted}");
    }
    // before a write, a SIMULATED label of the file it replaces is kept; once written, the new
    // entry is exact
    record_before_writing(dir.path(), vec![entry("b.v2.depth.png", false)]).unwrap();
    assert_eq!(simulated("b.v2.depth.png"), Some(true));
    record_aligned_files(dir.path(), vec![entry("b.v2.depth.png", false)]).unwrap();
    assert_eq!(simulated("b.v2.depth.png"), Some(false));
    record_before_writing(dir.path(), vec![entry("a.depth.npy", true)]).unwrap();
    assert_eq!(simulated("a.depth.npy"), Some(true));
    // writers from many threads at once, started together, lose no entry (the index's lock
    // file serialises them)
    for round in 0..5 {
        let start = std::sync::Barrier::new(8);
        std::thread::scope(|s| {
            for t in 0..8 {
                let (d, start) = (dir.path(), &start);
                s.spawn(move || {
                    start.wait();
                    let name = format!("r{round}t{t}.depth.npy");
                    record_aligned_files(d, vec![entry(&name, true)]).unwrap()
                });
            }
        });
    }
    let index = read_aligned_index(dir.path()).unwrap().unwrap();
    assert_eq!(index.files.len(), 3 + 5 * 8);
    assert!(dir.path().join(ALIGNED_LOCK_FILE).is_file());
    let path = dir.path().join(ALIGNED_INDEX_FILE);
    // another tool's file: says nothing to a reader, refused (untouched) by a writer
    for foreign in [r#"{"format": "moma-predictions"}"#, r#"{"results": []}"#] {
        std::fs::write(&path, foreign).unwrap();
        assert_eq!(of("a.depth.npy"), Provenance::ForeignIndex(path.clone()));
        let e = record_aligned_files(dir.path(), vec![entry("d", true)]).unwrap_err();
        assert!(e.to_string().contains("another tool's file"), "{e}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), foreign);
    }
    // moma's, but unreadable: an error for both
    for (text, says) in [
        (
            r#"{"format": "moma-aligned", "version": 2, "files": []}"#,
            "version 2",
        ),
        (
            r#"{"format": "moma-aligned", "version": 1}"#,
            "missing field `files`",
        ),
        ("{", "aligned.json"),
    ] {
        std::fs::write(&path, text).unwrap();
        let e = record_aligned_files(dir.path(), vec![entry("d", true)]).unwrap_err();
        assert!(e.to_string().contains(says), "{text}: {e}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), text);
        let e = provenance_of(&dir.path().join("a.depth.npy")).unwrap_err();
        assert!(e.to_string().contains(says), "{text}: {e}");
    }
    std::fs::remove_file(&path).unwrap();
    std::fs::create_dir(&path).unwrap();
    let e = provenance_of(&dir.path().join("a.depth.npy")).unwrap_err();
    assert!(e.to_string().contains("is not a file"), "{e}");
}

/// A described PNG keeps its pixels and its `Description` (characters outside Latin-1 spelt
/// out: `σ` as `sigma`); a PNG without one reads as `None`.
#[test]
fn a_described_png_keeps_its_pixels_and_its_description() {
    let dir = tempfile::tempdir().unwrap();
    let img = image::RgbImage::from_fn(5, 4, |x, y| image::Rgb([x as u8 * 40, y as u8 * 60, 7]));
    let path = dir.path().join("overlay.png");
    moma_io::write_rgb_png_described(&path, &img, "SIMULATED\nunder a uniform σ of 4.0 mm")
        .unwrap();
    assert_eq!(moma_io::read_rgb(&path).unwrap(), img);
    assert_eq!(
        moma_io::read_png_description(&path).unwrap().as_deref(),
        Some("SIMULATED\nunder a uniform sigma of 4.0 mm")
    );
    let plain = dir.path().join("plain.png");
    moma_io::write_rgb(&plain, &img).unwrap();
    assert_eq!(moma_io::read_png_description(&plain).unwrap(), None);
}
