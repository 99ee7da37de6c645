//! Latency of `moma ros2` per frame, and of the DDS transport alone, inside a network namespace
//! of its own (root; all traffic on `lo`).
//!
//! ```sh
//! cargo build --release -p moma-cli
//! moma simulate --set ../shared/data/graspnet6dof-table -o /tmp/preds
//! moma calibrate --pred /tmp/preds/blue_mug.npy --gt ../shared/data/graspnet6dof-table/frames/blue_mug/depth.png \
//!     --camera ../shared/data/graspnet6dof-table/camera.json -o /tmp/calib.json
//! sudo cargo run --release -p moma-ros2 --example ros2_latency -- target/release/moma \
//!     ../shared/data/graspnet6dof-table /tmp/preds /tmp/calib.json 100
//! ```
//!
//! 1. Transport: an echo participant sends every `Image` it receives back on another topic; the
//!    sender measures the round trip of a 640×480 `32FC1` image (1.2 MB) and of a point cloud's
//!    size (3.7 MB). Half of it is one hop's cost (serialise, fragment, send, reassemble,
//!    deserialise).
//! 2. The node: `moma ros2-replay` publishes SIMULATED predictions at 10 Hz, `moma ros2 --input
//!    prediction` aligns them; its diagnostics report per frame the time from taking the
//!    prediction to having published `depth`, and `points`.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use moma_ros2::dds::{self, Network};
use moma_ros2::msg::{self, DiagnosticArray, Header, Image, Time};
use ndarray::Array2;

const DOMAIN: u16 = 31;

fn private_network() {
    // SAFETY: unshare(2) with CLONE_NEWNET moves this (still single-threaded) process alone.
    let rc = unsafe { libc::unshare(libc::CLONE_NEWNET) };
    assert_eq!(
        rc,
        0,
        "unshare(CLONE_NEWNET) needs root: {}",
        std::io::Error::last_os_error()
    );
    for args in [
        &["link", "set", "lo", "up"][..],
        &["link", "set", "lo", "multicast", "on"],
        &["route", "add", "224.0.0.0/4", "dev", "lo"],
    ] {
        assert!(Command::new("ip").args(args).status().unwrap().success());
    }
}

fn quantiles(mut v: Vec<f64>) -> (f64, f64, usize) {
    v.sort_by(f64::total_cmp);
    let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
    (q(0.5), q(0.9), v.len())
}

/// Round trips of `Image`s of `rows × 640` float32 through an echo participant, milliseconds.
fn echo_round_trips(rows: usize, n: usize) -> Vec<f64> {
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let s = stop.clone();
    let echo = std::thread::spawn(move || {
        let mut node = dds::node("echo", "/", DOMAIN, Network::Loopback).unwrap();
        let qos = dds::sensor_qos();
        let sub = dds::subscription::<Image>(
            &mut node,
            "ping",
            msg::types::image(),
            &dds::sensor_reader_qos(),
        )
        .unwrap();
        let publ = dds::publisher::<Image>(&mut node, "pong", msg::types::image(), &qos).unwrap();
        while !s.load(std::sync::atomic::Ordering::Relaxed) {
            while let Ok(Some((m, _))) = sub.take() {
                dds::publish(&publ, m).unwrap();
            }
            std::thread::sleep(Duration::from_micros(100));
        }
    });
    let mut node = dds::node("pinger", "/", DOMAIN, Network::Loopback).unwrap();
    let publ = dds::publisher::<Image>(&mut node, "ping", msg::types::image(), &dds::sensor_qos())
        .unwrap();
    let sub = dds::subscription::<Image>(
        &mut node,
        "pong",
        msg::types::image(),
        &dds::sensor_reader_qos(),
    )
    .unwrap();
    std::thread::sleep(Duration::from_secs(3)); // discovery
    let values = Array2::<f32>::from_shape_fn((rows, 640), |(v, u)| (v * 640 + u) as f32);
    let mut rtts = Vec::new();
    for i in 0..n as i32 {
        let img = moma_ros2::convert::f32_to_image(
            &values,
            Header {
                stamp: Time { sec: i, nanosec: 0 },
                frame_id: "bench".into(),
            },
        );
        let t = Instant::now();
        dds::publish(&publ, img).unwrap();
        let deadline = t + Duration::from_secs(1);
        while Instant::now() < deadline {
            if let Ok(Some((m, _))) = sub.take()
                && m.header.stamp.sec == i
            {
                rtts.push(t.elapsed().as_secs_f64() * 1e3);
                break;
            }
            std::thread::sleep(Duration::from_micros(50));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    echo.join().unwrap();
    rtts
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 5 {
        eprintln!("usage: ros2_latency MOMA_BIN SET PREDS CALIB [FRAMES]");
        std::process::exit(2);
    }
    let frames: usize = args.get(5).and_then(|s| s.parse().ok()).unwrap_or(100);
    private_network();

    println!("| what | median | p90 | samples |");
    println!("|---|---:|---:|---:|");
    for (rows, what) in [
        (480, "echo round trip, 640×480 32FC1 (1.2 MB)"),
        (1440, "echo round trip, 3.7 MB (a 640×480 xyz cloud)"),
    ] {
        let (m, p, n) = quantiles(echo_round_trips(rows, 50));
        println!("| {what} | {m:.2} ms | {p:.2} ms | {n} |");
    }

    let dom = DOMAIN.to_string();
    let mut node = Command::new(&args[1])
        .args([
            "ros2",
            "--calib",
            &args[4],
            "--input",
            "prediction",
            "--localhost-only",
            "--domain-id",
            &dom,
        ])
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut me = dds::node("latency", "/", DOMAIN, Network::Loopback).unwrap();
    let diag = dds::subscription::<DiagnosticArray>(
        &mut me,
        "diagnostics",
        msg::types::diagnostic_array(),
        &dds::sensor_reader_qos(),
    )
    .unwrap();
    let mut replay = Command::new(&args[1])
        .args([
            "ros2-replay",
            "--set",
            &args[2],
            "--pred",
            &args[3],
            "--rate",
            "10",
            "--loop",
            "--max-frames",
            &frames.to_string(),
            "--localhost-only",
            "--domain-id",
            &dom,
            "--warmup-s",
            "3",
        ])
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let (mut depth_ms, mut points_ms, mut align_ms, mut cloud_ms) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let deadline = Instant::now() + Duration::from_secs(30 + frames as u64 / 5);
    while depth_ms.len() < frames.saturating_sub(5) && Instant::now() < deadline {
        while let Ok(Some((d, _))) = diag.take() {
            for kv in d.status.iter().flat_map(|s| &s.values) {
                match kv.key.as_str() {
                    "latency_depth_ms" => depth_ms.push(kv.value.parse().unwrap()),
                    "latency_points_ms" => points_ms.push(kv.value.parse().unwrap()),
                    "align_ms" => align_ms.push(kv.value.parse().unwrap()),
                    "cloud_ms" => cloud_ms.push(kv.value.parse().unwrap()),
                    _ => {}
                }
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let _ = replay.kill();
    let _ = node.kill();
    let _ = replay.wait();
    let _ = node.wait();
    let (m, p, n) = quantiles(depth_ms);
    println!("| moma ros2: prediction taken → depth published | {m:.2} ms | {p:.2} ms | {n} |");
    let (m, p, n) = quantiles(points_ms);
    println!("| moma ros2: prediction taken → points published | {m:.2} ms | {p:.2} ms | {n} |");
    let (m, p, n) = quantiles(align_ms);
    println!("| of which the alignment (`Calibration::aligned`) | {m:.2} ms | {p:.2} ms | {n} |");
    let (m, p, n) = quantiles(cloud_ms);
    println!("| of which building the cloud | {m:.2} ms | {p:.2} ms | {n} |");
}
