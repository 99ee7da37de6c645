//! Messages against hand-written CDR bytes, and conversions against closed forms.

use byteorder::LittleEndian;
use moma_core::{Intrinsics, MetricDepth};
use moma_ros2::RosError;
use moma_ros2::convert::{
    camera_info_to_intrinsics, depth_image_to_metres, depth_to_cloud, depth_to_image,
    depth_to_mm_image, grasp_pose, image_to_f32, image_to_rgb, intrinsics_to_camera_info,
};
use moma_ros2::msg::{CameraInfo, Header, Image, Quaternion, Time};
use ndarray::{Array2, array};
use serde_bytes::ByteBuf;

fn header() -> Header {
    Header {
        stamp: Time { sec: 7, nanosec: 9 },
        frame_id: "cam".into(),
    }
}

/// The CDR (little-endian, XCDR1) bytes of a `sensor_msgs/Image`, written out field by field as
/// the OMG spec and rmw lay them out: 4-byte alignment for u32, strings with their NUL.
#[test]
fn image_cdr_layout_matches_the_spec() {
    let img = Image {
        header: header(),
        height: 1,
        width: 2,
        encoding: "mono8".into(),
        is_bigendian: 0,
        step: 2,
        data: ByteBuf::from(vec![10u8, 20]),
    };
    let bytes = cdr_encoding::to_vec::<_, LittleEndian>(&img).unwrap();
    let mut want = Vec::new();
    want.extend(7i32.to_le_bytes());
    want.extend(9u32.to_le_bytes());
    want.extend(4u32.to_le_bytes()); // "cam" + NUL
    want.extend(b"cam\0");
    want.extend(1u32.to_le_bytes());
    want.extend(2u32.to_le_bytes());
    want.extend(6u32.to_le_bytes()); // "mono8" + NUL
    want.extend(b"mono8\0");
    want.push(0); // is_bigendian at offset 34
    want.push(0); // padding to 36, the step's alignment
    want.extend(2u32.to_le_bytes()); // step
    want.extend(2u32.to_le_bytes()); // data length
    want.extend([10u8, 20]);
    assert_eq!(bytes, want);
    let (back, used): (Image, usize) = cdr_encoding::from_bytes::<_, LittleEndian>(&bytes).unwrap();
    assert_eq!(back, img);
    assert_eq!(used, bytes.len());
}

/// A truncated message does not decode (no panic).
#[test]
fn truncated_cdr_is_an_error() {
    let img = Image {
        header: header(),
        height: 2,
        width: 2,
        encoding: "rgb8".into(),
        is_bigendian: 0,
        step: 6,
        data: ByteBuf::from(vec![1u8; 12]),
    };
    let bytes = cdr_encoding::to_vec::<_, LittleEndian>(&img).unwrap();
    for cut in [0, 3, 10, bytes.len() - 1] {
        let r = cdr_encoding::from_bytes::<Image, LittleEndian>(&bytes[..cut]);
        assert!(r.is_err(), "cut at {cut} decoded");
    }
}

fn colour(encoding: &str, step: u32, data: Vec<u8>) -> Image {
    Image {
        header: header(),
        height: 2,
        width: 2,
        encoding: encoding.into(),
        is_bigendian: 0,
        step,
        data: ByteBuf::from(data),
    }
}

#[test]
fn colour_encodings_give_rgb() {
    // 2×2, pixel i has r = 10 i + 1, g = 10 i + 2, b = 10 i + 3
    let rgb: Vec<[u8; 3]> = (0..4u8)
        .map(|i| [10 * i + 1, 10 * i + 2, 10 * i + 3])
        .collect();
    let want: Vec<u8> = rgb.iter().flatten().copied().collect();
    // bgr8 with 2 bytes of row padding
    let mut bgr = Vec::new();
    for row in 0..2 {
        for col in 0..2 {
            let [r, g, b] = rgb[row * 2 + col];
            bgr.extend([b, g, r]);
        }
        bgr.extend([0xEE, 0xEE]);
    }
    assert_eq!(
        image_to_rgb(&colour("bgr8", 8, bgr)).unwrap().into_raw(),
        want
    );
    let rgba: Vec<u8> = rgb.iter().flat_map(|p| [p[0], p[1], p[2], 255]).collect();
    assert_eq!(
        image_to_rgb(&colour("rgba8", 8, rgba)).unwrap().into_raw(),
        want
    );
    let bgra: Vec<u8> = rgb.iter().flat_map(|p| [p[2], p[1], p[0], 255]).collect();
    assert_eq!(
        image_to_rgb(&colour("bgra8", 8, bgra)).unwrap().into_raw(),
        want
    );
    let mono = image_to_rgb(&colour("mono8", 2, vec![5, 6, 7, 8])).unwrap();
    assert_eq!(mono.get_pixel(1, 1).0, [8, 8, 8]);
}

#[test]
fn bad_images_are_errors_naming_the_problem() {
    let e = image_to_rgb(&colour("yuv422", 4, vec![0; 8])).unwrap_err();
    assert!(matches!(e, RosError::Encoding { .. }), "{e}");
    assert!(e.to_string().contains("yuv422"));
    // truncated: 2 rows of 6 bytes need 12
    let e = image_to_rgb(&colour("rgb8", 6, vec![0; 11])).unwrap_err();
    assert!(e.to_string().contains("truncated"), "{e}");
    // step shorter than a row
    let e = image_to_rgb(&colour("rgb8", 5, vec![0; 12])).unwrap_err();
    assert!(e.to_string().contains("step"), "{e}");
    // absurd size, refused before allocating
    let mut huge = colour("rgb8", 6, vec![0; 12]);
    huge.width = u32::MAX;
    huge.height = u32::MAX;
    huge.step = u32::MAX;
    assert!(image_to_rgb(&huge).is_err());
    // empty
    let mut empty = colour("rgb8", 6, vec![]);
    empty.height = 0;
    assert!(image_to_rgb(&empty).is_err());
    // a prediction of another encoding
    assert!(image_to_f32(&colour("rgb8", 6, vec![0; 12])).is_err());
}

#[test]
fn float_and_depth_images_round_trip() {
    let values = array![[1.5f32, -2.0, f32::NAN], [0.0, 3.25, 1e-3]];
    let img = moma_ros2::convert::f32_to_image(&values, header());
    assert_eq!(img.step, 12);
    let back = image_to_f32(&img).unwrap();
    for (a, b) in values.iter().zip(&back) {
        assert_eq!(a.to_bits(), b.to_bits());
    }
    // big-endian 32FC1
    let mut be = img.clone();
    be.is_bigendian = 1;
    be.data = ByteBuf::from(
        values
            .iter()
            .flat_map(|v| v.to_be_bytes())
            .collect::<Vec<u8>>(),
    );
    assert_eq!(image_to_f32(&be).unwrap()[[1, 1]], 3.25);
    // depth: 32FC1 invalid → NaN
    let depth = MetricDepth::new(array![[0.5f32, 0.0], [f32::NAN, 2.0]]);
    let img = depth_to_image(&depth, header());
    let back = depth_image_to_metres(&img).unwrap();
    assert_eq!(back.depth_m[[0, 0]], 0.5);
    assert!(back.depth_m[[0, 1]].is_nan());
    assert!(back.depth_m[[1, 0]].is_nan());
    // 16UC1 millimetres
    let mm = depth_to_mm_image(
        &MetricDepth::new(array![[0.5f32, 0.0], [1.234, 70.0]]),
        header(),
    );
    assert_eq!(mm.encoding, "16UC1");
    let back = depth_image_to_metres(&mm).unwrap();
    // as moma_io reads a depth PNG: v / 1000 in f64, then f32
    assert_eq!(back.depth_m[[0, 0]], 0.5f32);
    assert_eq!(back.depth_m[[1, 0]], (1234.0f64 / 1000.0) as f32);
    assert!(back.depth_m[[0, 1]].is_nan(), "0 mm is no depth");
    assert!(back.depth_m[[1, 1]].is_nan(), "beyond 65.535 m is no depth");
}

fn camera() -> Intrinsics {
    Intrinsics {
        width: 3,
        height: 2,
        fx: 500.0,
        fy: 400.0,
        cx: 1.0,
        cy: 0.5,
    }
}

#[test]
fn camera_info_round_trips_and_rejects_zero_focal() {
    let info = intrinsics_to_camera_info(&camera(), header());
    assert_eq!(camera_info_to_intrinsics(&info).unwrap(), camera());
    // an uncalibrated driver's all-zero K and P
    let mut bad = info.clone();
    bad.k[0] = 0.0;
    bad.p[0] = 0.0;
    let e = camera_info_to_intrinsics(&bad).unwrap_err();
    assert!(e.to_string().contains("fx"), "{e}");
    let mut bad = info;
    bad.width = 0;
    assert!(camera_info_to_intrinsics(&bad).is_err());
}

/// A 640×480 sensor whose raw image has distortion: K is the raw image's, P the rectified one's.
fn distorted_camera_info() -> CameraInfo {
    let mut info = intrinsics_to_camera_info(
        &Intrinsics {
            width: 640,
            height: 480,
            fx: 610.0,
            fy: 605.0,
            cx: 318.0,
            cy: 242.0,
        },
        header(),
    );
    info.d = vec![0.1, -0.2, 0.001, 0.002, 0.0];
    info.p = [
        580.0, 0.0, 321.0, 0.0, 0.0, 578.0, 239.0, 0.0, 0.0, 0.0, 1.0, 0.0,
    ];
    info
}

#[test]
fn camera_info_gives_the_rectified_images_intrinsics() {
    // image_geometry's PinholeCameraModel::fx() etc. read P: a rectified image's intrinsics
    let info = distorted_camera_info();
    let k = camera_info_to_intrinsics(&info).unwrap();
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (580.0, 578.0, 321.0, 239.0));
    assert_eq!((k.width, k.height), (640, 480));
    // a driver that leaves P unset: K
    let mut no_p = info;
    no_p.p = [0.0; 12];
    let k = camera_info_to_intrinsics(&no_p).unwrap();
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (610.0, 605.0, 318.0, 242.0));
}

#[test]
fn binning_and_region_of_interest_reduce_the_intrinsics() {
    // 2×2 binning of the full image: a 320×240 image; a point at camera (x, y, z) projects to
    // the full image's pixel halved
    let mut info = distorted_camera_info();
    info.binning_x = 2;
    info.binning_y = 2;
    let k = camera_info_to_intrinsics(&info).unwrap();
    assert_eq!((k.width, k.height), (320, 240));
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (290.0, 289.0, 160.5, 119.5));
    let (x, y, z) = (0.05_f64, -0.03, 0.8);
    let full = (580.0 * x / z + 321.0, 578.0 * y / z + 239.0);
    let binned = (k.fx * x / z + k.cx, k.fy * y / z + k.cy);
    assert!((binned.0 - full.0 / 2.0).abs() < 1e-12 && (binned.1 - full.1 / 2.0).abs() < 1e-12);
    // a 200×100 region at (100, 50), no binning: the principal point moves by the offset
    let mut info = distorted_camera_info();
    info.roi.x_offset = 100;
    info.roi.y_offset = 50;
    info.roi.width = 200;
    info.roi.height = 100;
    let k = camera_info_to_intrinsics(&info).unwrap();
    assert_eq!((k.width, k.height), (200, 100));
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (580.0, 578.0, 221.0, 189.0));
    // the region and 2×2 binning: cropped in full-resolution pixels, then binned
    info.binning_x = 2;
    info.binning_y = 2;
    let k = camera_info_to_intrinsics(&info).unwrap();
    assert_eq!((k.width, k.height), (100, 50));
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (290.0, 289.0, 110.5, 94.5));
    // binning 0 and 1 both mean none
    let mut info = distorted_camera_info();
    info.binning_x = 1;
    info.binning_y = 0;
    assert_eq!(camera_info_to_intrinsics(&info).unwrap().width, 640);
    // a region of no size that is not all zero (image_geometry's full-image marker) is
    // malformed: an empty image
    let mut empty = distorted_camera_info();
    empty.roi.x_offset = 10;
    let e = camera_info_to_intrinsics(&empty).unwrap_err().to_string();
    assert!(e.contains("empty"), "{e}");
    // a region outside the image is malformed, named
    info.roi.x_offset = 600;
    info.roi.width = 100;
    info.roi.height = 10;
    let e = camera_info_to_intrinsics(&info).unwrap_err().to_string();
    assert!(e.contains("region of interest 100×10 at (600, 0)"), "{e}");
}

fn read_f32(data: &[u8], at: usize) -> f32 {
    f32::from_le_bytes([data[at], data[at + 1], data[at + 2], data[at + 3]])
}

#[test]
fn organised_cloud_is_the_pinhole_back_projection() {
    let depth = MetricDepth::new(Array2::from_shape_fn((2, 3), |(v, u)| {
        if (v, u) == (1, 2) {
            f32::NAN
        } else {
            1.0 + 0.25 * (v * 3 + u) as f32
        }
    }));
    let rgb = image::RgbImage::from_fn(3, 2, |u, v| image::Rgb([u as u8, v as u8, 200]));
    let cloud = depth_to_cloud(&depth, &camera(), Some(&rgb), header()).unwrap();
    assert_eq!((cloud.height, cloud.width, cloud.point_step), (2, 3, 16));
    assert_eq!(cloud.row_step, 48);
    assert!(!cloud.is_dense);
    let names: Vec<&str> = cloud.fields.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["x", "y", "z", "rgb"]);
    for v in 0..2usize {
        for u in 0..3usize {
            let at = (v * 3 + u) * 16;
            let z = depth.depth_m[[v, u]];
            let (x, y, zz) = (
                read_f32(&cloud.data, at),
                read_f32(&cloud.data, at + 4),
                read_f32(&cloud.data, at + 8),
            );
            if z.is_nan() {
                assert!(x.is_nan() && y.is_nan() && zz.is_nan());
            } else {
                // x = (u − cx) z / fx, y = (v − cy) z / fy
                assert!((x - (u as f32 - 1.0) * z / 500.0).abs() < 1e-7);
                assert!((y - (v as f32 - 0.5) * z / 400.0).abs() < 1e-7);
                assert_eq!(zz, z);
            }
            let packed = u32::from_le_bytes(cloud.data[at + 12..at + 16].try_into().unwrap());
            assert_eq!(packed, ((u as u32) << 16) | ((v as u32) << 8) | 200);
        }
    }
    // without colour: 12 bytes a point; a camera of another size is an error
    let plain = depth_to_cloud(&depth, &camera(), None, header()).unwrap();
    assert_eq!(plain.point_step, 12);
    let mut other = camera();
    other.width = 4;
    assert!(depth_to_cloud(&depth, &other, None, header()).is_err());
}

/// Rotates `v` by the unit quaternion `q` (v' = q v q*), written out independently of the
/// crate's matrix-to-quaternion code.
fn rotate(q: &Quaternion, v: [f64; 3]) -> [f64; 3] {
    let (w, x, y, z) = (q.w, q.x, q.y, q.z);
    let m = [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ];
    [0, 1, 2].map(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2])
}

#[test]
fn grasp_pose_x_is_approach_and_y_is_closing() {
    let cases: [([f32; 3], Option<[f32; 3]>); 5] = [
        ([0.0, 0.0, 1.0], Some([1.0, 0.0, 0.0])),
        ([0.0, 0.0, -1.0], Some([0.0, 1.0, 0.0])),
        ([0.6, 0.0, 0.8], Some([0.0, 1.0, 0.0])),
        ([1.0, 0.0, 0.0], None),
        ([-0.3, 0.5, 0.812], Some([0.9, 0.3, 0.2])),
    ];
    for (approach, closing) in cases {
        let pose = grasp_pose([0.1, 0.2, 0.3], approach, closing);
        let q = pose.orientation;
        let n = (q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z).sqrt();
        assert!((n - 1.0).abs() < 1e-9);
        let a: Vec<f64> = approach.iter().map(|&c| f64::from(c)).collect();
        let na = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        let x = rotate(&q, [1.0, 0.0, 0.0]);
        for i in 0..3 {
            assert!(
                (x[i] - a[i] / na).abs() < 1e-6,
                "{approach:?}: x axis {x:?}"
            );
        }
        let y = rotate(&q, [0.0, 1.0, 0.0]);
        assert!(y.iter().zip(&a).map(|(p, q)| p * q).sum::<f64>().abs() < 1e-6);
        if let Some(c) = closing {
            // y is the closing direction made orthogonal to the approach: positive along it
            let dot: f64 = y.iter().zip(c).map(|(p, q)| p * f64::from(q)).sum();
            assert!(dot > 0.0);
        }
        assert_eq!(pose.position.z, f64::from(0.3f32));
    }
}

proptest::proptest! {
    /// Whatever an image message claims, the conversions return a value or an error, never a
    /// panic, and a value has the claimed size.
    #[test]
    fn arbitrary_images_never_panic(
        w in 0u32..40,
        h in 0u32..40,
        step in 0u32..200,
        len in 0usize..5000,
        enc in proptest::sample::select(vec!["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "32FC1", "16UC1", "yuv422", ""]),
        big in 0u8..3,
    ) {
        let img = Image {
            header: header(),
            height: h,
            width: w,
            encoding: enc.to_string(),
            is_bigendian: big,
            step,
            data: ByteBuf::from(vec![0x41u8; len]),
        };
        if let Ok(rgb) = image_to_rgb(&img) {
            proptest::prop_assert_eq!((rgb.width(), rgb.height()), (w, h));
        }
        if let Ok(v) = image_to_f32(&img) {
            proptest::prop_assert_eq!(v.dim(), (h as usize, w as usize));
        }
        if let Ok(d) = depth_image_to_metres(&img) {
            proptest::prop_assert_eq!(d.depth_m.dim(), (h as usize, w as usize));
        }
    }
}

#[test]
fn a_topic_name_ros_refuses_is_explained() {
    for (name, says) in [
        ("", "a topic name cannot be empty"),
        ("bad topic", "' ' is not allowed in a topic name"),
        // the character in the name, not one ros2-client reports in its place
        ("~/depth", "'~' is not allowed in a topic name"),
        ("~/depth", "give the full name, e.g. /moma/depth"),
        ("cam/image-raw", "'-' is not allowed"),
        ("cam/2d", "cannot start with a digit"),
    ] {
        let e = moma_ros2::dds::topic_name(name).unwrap_err().to_string();
        assert!(e.contains(says) && !e.contains("BadChar"), "{name:?}: {e}");
    }
    assert!(moma_ros2::dds::topic_name("/camera/color/image_raw").is_ok());
}
