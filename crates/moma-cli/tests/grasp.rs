//! `moma grasp` end to end on a synthetic scene written to a temp dir: a 40 × 70 × 50 mm box on a
//! table 0.7 m below a top-down camera (depth rendered in closed form: the box top at 0.65 m).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use moma_core::{Intrinsics, MetricDepth};
use ndarray::Array2;

const W: usize = 640;
const H: usize = 480;

fn moma(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_moma"))
        .args(args)
        .output()
        .expect("the moma binary runs")
}

fn ok(args: &[&str]) -> (String, String) {
    let out = moma(args);
    assert!(
        out.status.success(),
        "moma {args:?} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    (
        String::from_utf8(out.stdout).unwrap(),
        String::from_utf8(out.stderr).unwrap(),
    )
}

fn fails(args: &[&str]) -> String {
    let out = moma(args);
    assert!(!out.status.success(), "moma {args:?} should fail");
    String::from_utf8(out.stderr).unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn camera() -> Intrinsics {
    Intrinsics {
        width: W,
        height: H,
        fx: 600.0,
        fy: 600.0,
        cx: 319.5,
        cy: 239.5,
    }
}

/// Box footprint |x| < 20 mm, |y| < 35 mm around the optical axis; `with_box = false`: bare table.
fn scene(dir: &Path, with_box: bool) -> (PathBuf, PathBuf) {
    let k = camera();
    let depth = Array2::from_shape_fn((H, W), |(v, u)| {
        let (x, y) = (
            (u as f64 - k.cx) / k.fx * 0.65,
            (v as f64 - k.cy) / k.fy * 0.65,
        );
        if with_box && x.abs() < 0.02 && y.abs() < 0.035 {
            0.65f32
        } else {
            0.7
        }
    });
    let depth_path = dir.join(if with_box { "box.png" } else { "table.png" });
    moma_io::write_depth(&depth_path, &MetricDepth::new(depth)).unwrap();
    let cam = dir.join("camera.json");
    moma_io::write_camera(&cam, &k).unwrap();
    (depth_path, cam)
}

#[test]
fn parallel_json_closes_across_the_box() {
    let dir = tempfile::tempdir().unwrap();
    let (depth, cam) = scene(dir.path(), true);
    let (out, _) = ok(&[
        "grasp",
        "--depth",
        s(&depth),
        "--camera",
        s(&cam),
        "--gripper",
        "parallel",
        "--json",
    ]);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let arr = v.as_array().unwrap();
    assert!(!arr.is_empty() && arr.len() <= 10);
    let g = arr[0].as_object().unwrap();
    let keys: Vec<&str> = g.keys().map(|k| k.as_str()).collect();
    let mut sorted = keys.clone();
    sorted.sort_unstable();
    assert_eq!(
        sorted,
        [
            "approach",
            "center_m",
            "closing",
            "kind",
            "score",
            "success_prob",
            "width_m"
        ]
    );
    assert_eq!(g["kind"], "parallel");
    assert!(
        g["success_prob"].is_null(),
        "no error model: no probability"
    );
    let w = g["width_m"].as_f64().unwrap();
    assert!((0.04..=0.085).contains(&w), "width {w}");
    let closing: Vec<f64> = serde_json::from_value(g["closing"].clone()).unwrap();
    assert!(
        closing[0].abs() > 0.95,
        "closing {closing:?} not across the 40 mm side (x)"
    );
    let c: Vec<f64> = serde_json::from_value(g["center_m"].clone()).unwrap();
    assert!(
        c[0].abs() < 0.005 && (c[2] - 0.65).abs() < 0.006,
        "centre {c:?}"
    );
    // Best first.
    let scores: Vec<f64> = arr.iter().map(|g| g["score"].as_f64().unwrap()).collect();
    assert!(scores.windows(2).all(|w| w[0] >= w[1]));
}

/// `&str`s of owned arguments.
fn strs(a: &[String]) -> Vec<&str> {
    a.iter().map(String::as_str).collect()
}

#[test]
fn suction_with_extrinsics_and_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let (depth, cam) = scene(dir.path(), true);
    // Camera 1 m above the base origin looking down: base = (x, −y, 1 − z).
    let ext = dir.path().join("camera_to_base.json");
    std::fs::write(
        &ext,
        r#"{"camera_to_base": [[1,0,0,0],[0,-1,0,0],[0,0,-1,1],[0,0,0,1]]}"#,
    )
    .unwrap();
    let out_dir = dir.path().join("out");
    // `grasp --depth D --camera C --gripper suction` followed by `extra`
    let suction = |extra: &[&str]| -> Vec<String> {
        let base = ["grasp", "--depth", s(&depth), "--camera", s(&cam)];
        base.iter()
            .chain(&["--gripper", "suction"])
            .chain(extra)
            .map(|x| x.to_string())
            .collect()
    };
    let (out, _) = ok(&strs(&suction(&[
        "--extrinsics",
        s(&ext),
        "--top",
        "3",
        "--json",
        "-o",
        s(&out_dir),
    ])));
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let arr = v.as_array().unwrap();
    assert!(!arr.is_empty() && arr.len() <= 3);
    for g in arr {
        assert_eq!(g["kind"], "suction");
        let p: Vec<f64> = serde_json::from_value(g["point_m"].clone()).unwrap();
        let b: Vec<f64> = serde_json::from_value(g["base"]["point_m"].clone()).unwrap();
        assert!(
            (b[0] - p[0]).abs() < 1e-5
                && (b[1] + p[1]).abs() < 1e-5
                && (b[2] - (1.0 - p[2])).abs() < 1e-5
        );
        assert!(
            (p[2] - 0.65).abs() < 0.002,
            "suction point {p:?} not on the box top"
        );
        let a: Vec<f64> = serde_json::from_value(g["approach"].clone()).unwrap();
        assert!(
            a[2] > 0.996,
            "approach {a:?} not straight down (into the surface)"
        );
    }
    let written: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out_dir.join("grasps.json")).unwrap()).unwrap();
    assert_eq!(written, v);
    // the human summary shows the base frame too: the best grasp's point as in the JSON
    let (text, _) = ok(&strs(&suction(&["--extrinsics", s(&ext), "--top", "1"])));
    let b: Vec<f64> = serde_json::from_value(arr[0]["base"]["point_m"].clone()).unwrap();
    let want = format!(
        "base frame:  point [{:+.3}, {:+.3}, {:+.3}]",
        b[0], b[1], b[2]
    );
    assert!(text.contains(&want), "{text}\nwants {want}");
    let overlay = moma_io::read_rgb(out_dir.join("overlay.png")).unwrap();
    // the frame's pixels on top, a caption strip below (title lines and one line per grasp):
    // mostly its dark ground, with text
    assert_eq!(overlay.width(), W as u32);
    assert!(overlay.height() > H as u32, "no caption strip");
    let strip: Vec<[u8; 3]> = (H as u32..overlay.height())
        .flat_map(|v| (0..W as u32).map(move |u| (u, v)))
        .map(|(u, v)| overlay.get_pixel(u, v).0)
        .collect();
    let ground = strip.iter().filter(|p| **p == [28, 28, 28]).count();
    assert!(
        ground * 10 > strip.len() * 7 && ground < strip.len(),
        "{ground} of {} strip pixels are its ground",
        strip.len()
    );
    // The best grasp is drawn in green at its projected point.
    let p: Vec<f64> = serde_json::from_value(arr[0]["point_m"].clone()).unwrap();
    let k = camera();
    let (u, vv) = (k.fx * p[0] / p[2] + k.cx, k.fy * p[1] / p[2] + k.cy);
    assert_eq!(
        overlay.get_pixel(u.round() as u32, vv.round() as u32).0,
        [0, 230, 0]
    );
    let ply = std::fs::read(out_dir.join("scene.ply")).unwrap();
    let text = String::from_utf8_lossy(&ply[..300]);
    assert!(text.starts_with("ply\nformat binary_little_endian 1.0"));
    assert!(text.contains(&format!("element vertex {}", W * H + 8 * arr.len())));
    assert!(text.contains(&format!("element face {}", 12 * arr.len())));

    // --overlay-rgb: the overlay is drawn on the frame's colour image (a sensor's rgb.png beside
    // its depth): away from the grasps its pixels are the image's; one of another size is refused
    let rgb = dir.path().join("rgb.png");
    let frame = image::RgbImage::from_fn(W as u32, H as u32, |u, v| {
        image::Rgb([(u % 251) as u8, (v % 241) as u8, 90])
    });
    moma_io::write_rgb(&rgb, &frame).unwrap();
    let on_rgb = dir.path().join("on-rgb");
    ok(&strs(&suction(&[
        "--overlay-rgb",
        s(&rgb),
        "-o",
        s(&on_rgb),
    ])));
    let overlay = moma_io::read_rgb(on_rgb.join("overlay.png")).unwrap();
    let same = (0..H as u32)
        .flat_map(|v| (0..W as u32).map(move |u| (u, v)))
        .filter(|&(u, v)| overlay.get_pixel(u, v) == frame.get_pixel(u, v))
        .count();
    assert!(
        same * 10 > W * H * 9,
        "{same} of {} pixels are the image's",
        W * H
    );
    let small = dir.path().join("small.png");
    moma_io::write_rgb(&small, &image::RgbImage::new(32, 24)).unwrap();
    let o = moma(&strs(&suction(&[
        "--overlay-rgb",
        s(&small),
        "-o",
        s(&on_rgb),
    ])));
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(
        !o.status.success() && err.contains("--overlay-rgb"),
        "{err}"
    );

    // A second run into the same folder whose overlay cannot be written (a folder stands at its
    // path) fails, and leaves no grasps.json of the first run beside its own new depth.npy.
    std::fs::remove_file(out_dir.join("overlay.png")).unwrap();
    std::fs::create_dir(out_dir.join("overlay.png")).unwrap();
    let o = moma(&strs(&suction(&[
        "--extrinsics",
        s(&ext),
        "-o",
        s(&out_dir),
    ])));
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("overlay.png"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(!out_dir.join("grasps.json").exists());
    // depth-model options with --depth would be ignored: refused by name
    let o = moma(&strs(&suction(&["--weights", "w.pth", "--dtype", "int8"])));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("--weights, --dtype: depth-model options"),
        "{e}"
    );
}

/// Two 40 × 70 × 50 mm boxes side by side, touching along x = 0 (one flat 80 mm top in the
/// depth), told apart by an instance label mask (grey levels 100 and 200): every grasp stays
/// on one box. As one 0/255 mask they are one object, and the best suction grasps sit on the
/// seam.
#[test]
fn an_instance_label_mask_keeps_touching_objects_apart() {
    let dir = tempfile::tempdir().unwrap();
    let k = camera();
    let xy = |v: usize, u: usize| {
        (
            (u as f64 - k.cx) / k.fx * 0.65,
            (v as f64 - k.cy) / k.fy * 0.65,
        )
    };
    let depth = Array2::from_shape_fn((H, W), |(v, u)| {
        let (x, y) = xy(v, u);
        if x.abs() < 0.04 && y.abs() < 0.035 {
            0.65f32
        } else {
            0.7
        }
    });
    let depth_path = dir.path().join("two.png");
    moma_io::write_depth(&depth_path, &MetricDepth::new(depth)).unwrap();
    let cam = dir.path().join("camera.json");
    moma_io::write_camera(&cam, &k).unwrap();
    let mask = |levels: [u8; 2]| {
        image::GrayImage::from_fn(W as u32, H as u32, |u, v| {
            let (x, y) = xy(v as usize, u as usize);
            let level = if x.abs() < 0.04 && y.abs() < 0.035 {
                levels[usize::from(x >= 0.0)]
            } else {
                0
            };
            image::Luma([level])
        })
    };
    let plan = |name: &str, levels: [u8; 2], gripper: &str| {
        let path = dir.path().join(name);
        mask(levels).save(&path).unwrap();
        let (out, _) = ok(&[
            "grasp",
            "--depth",
            s(&depth_path),
            "--camera",
            s(&cam),
            "--mask",
            s(&path),
            "--gripper",
            gripper,
            "--top",
            "5",
            "--json",
        ]);
        serde_json::from_str::<Vec<serde_json::Value>>(&out).unwrap()
    };
    let x_of = |g: &serde_json::Value, key: &str| g[key][0].as_f64().unwrap();
    let labels = plan("labels.png", [100, 200], "suction");
    assert!(!labels.is_empty());
    for g in &labels {
        // the cup (10 mm radius) on one box: its centre at least a radius from the seam
        let x = x_of(g, "point_m");
        assert!(
            x.abs() >= 0.01,
            "suction on the seam between two objects: x = {x}"
        );
    }
    for g in &plan("labels.png", [100, 200], "parallel") {
        // the fingers close on one box: the contacts' span lies on one side of the seam
        let (x, w) = (x_of(g, "center_m"), g["width_m"].as_f64().unwrap());
        let closing_x = g["closing"][0].as_f64().unwrap().abs();
        assert!(
            x.abs() >= 0.5 * (w * closing_x).min(0.04) - 0.003,
            "a parallel grasp straddles the seam: centre x = {x}, width {w}, |closing x| \
             {closing_x}"
        );
        assert!(x.abs() > 0.005, "centre on the seam: {x}");
    }
    let binary = plan("binary.png", [255, 255], "suction");
    assert!(
        binary.iter().any(|g| x_of(g, "point_m").abs() < 0.01),
        "as one object the seam is no edge: {binary:?}"
    );
}

/// A depth PNG in 0.1 mm units (a RealSense D405's) read as millimetres puts the box scene's
/// table at 7 m: planned as read, with a note naming the likely unit; the scene in millimetres
/// gets none.
#[test]
fn depth_beyond_reach_is_noted_with_the_likely_unit() {
    let dir = tempfile::tempdir().unwrap();
    let (depth, cam) = scene(dir.path(), true);
    let args = |d: &Path| {
        let mut a = vec!["grasp", "--depth", s(d), "--camera", s(&cam)];
        a.extend(["--gripper", "suction", "--json"]);
        a.into_iter().map(str::to_string).collect::<Vec<_>>()
    };
    let run = |d: &Path| {
        let a = args(d);
        ok(&a.iter().map(String::as_str).collect::<Vec<_>>()).1
    };
    assert!(!run(&depth).contains("beyond a robot arm's reach"));
    let tenth = dir.path().join("tenth_mm.png");
    let read = moma_io::read_depth(&depth).unwrap();
    moma_io::write_depth(&tenth, &MetricDepth::new(read.depth_m.mapv(|z| z * 10.0))).unwrap();
    let err = run(&tenth);
    assert!(
        err.contains("median depth of")
            && err.contains("7.00 m, beyond a robot arm's reach")
            && err.contains("0.1 mm"),
        "{err}"
    );
}

#[test]
fn bare_table_gives_an_empty_list_and_a_reason() {
    let dir = tempfile::tempdir().unwrap();
    let (depth, cam) = scene(dir.path(), false);
    let (out, err) = ok(&[
        "grasp",
        "--depth",
        s(&depth),
        "--camera",
        s(&cam),
        "--gripper",
        "suction",
        "--json",
    ]);
    assert_eq!(out.trim(), "[]");
    assert!(
        err.contains("no grasp found") && err.contains("no object"),
        "{err}"
    );
}

#[test]
fn bad_inputs_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let (depth, cam) = scene(dir.path(), true);
    let base = [
        "grasp",
        "--depth",
        s(&depth),
        "--camera",
        s(&cam),
        "--gripper",
        "parallel",
    ];
    let run = |extra: &[&str]| {
        let mut a: Vec<&str> = base.to_vec();
        a.extend_from_slice(extra);
        fails(&a)
    };
    let ext = dir.path().join("scaled.json");
    std::fs::write(
        &ext,
        r#"{"camera_to_base": [[2,0,0,0],[0,2,0,0],[0,0,2,0],[0,0,0,1]]}"#,
    )
    .unwrap();
    let err = run(&["--extrinsics", s(&ext)]);
    assert!(
        err.contains("scaled.json") && err.contains("rigid"),
        "{err}"
    );

    let cfg = dir.path().join("jaw.json");
    std::fs::write(&cfg, r#"{"stroke_m": -0.05}"#).unwrap();
    let err = run(&["--gripper-config", s(&cfg)]);
    assert!(
        err.contains("jaw.json") && err.contains("stroke_m"),
        "{err}"
    );
    // A stroke no gripper has: refused, not planned for ever.
    std::fs::write(&cfg, r#"{"stroke_m": 1e30}"#).unwrap();
    let err = run(&["--gripper-config", s(&cfg)]);
    assert!(
        err.contains("jaw.json") && err.contains("stroke_m") && err.contains("at most 1 m"),
        "{err}"
    );

    let small = dir.path().join("small.json");
    moma_io::write_camera(
        &small,
        &Intrinsics {
            width: 320,
            height: 240,
            ..camera()
        },
    )
    .unwrap();
    let err = fails(&[
        "grasp",
        "--depth",
        s(&depth),
        "--camera",
        s(&small),
        "--gripper",
        "suction",
    ]);
    assert!(
        err.contains("small.json") && err.contains("box.png"),
        "{err}"
    );

    let zeros = dir.path().join("zeros.png");
    moma_io::write_depth(&zeros, &MetricDepth::new(Array2::zeros((H, W)))).unwrap();
    let err = fails(&[
        "grasp",
        "--depth",
        s(&zeros),
        "--camera",
        s(&cam),
        "--gripper",
        "suction",
    ]);
    assert!(
        err.contains("zeros.png") && err.contains("no valid depth"),
        "{err}"
    );

    // A mask over a region with no depth.
    let holes = dir.path().join("holes.png");
    let mut d = Array2::from_elem((H, W), 0.7f32);
    d.slice_mut(ndarray::s![0..20, 0..20]).fill(0.0);
    moma_io::write_depth(&holes, &MetricDepth::new(d)).unwrap();
    let mut m = Array2::from_elem((H, W), false);
    m.slice_mut(ndarray::s![0..20, 0..20]).fill(true);
    let mask = dir.path().join("mask.png");
    moma_io::write_mask(&mask, &moma_core::Mask::new(m)).unwrap();
    let err = fails(&[
        "grasp",
        "--depth",
        s(&holes),
        "--camera",
        s(&cam),
        "--gripper",
        "suction",
        "--mask",
        s(&mask),
    ]);
    assert!(
        err.contains("mask.png") && err.contains("none of them has valid depth"),
        "{err}"
    );
}
