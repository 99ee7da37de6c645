//! What the node spends per 640×480 frame outside the alignment: the `32FC1` depth image, the
//! organised cloud, and their CDR encoding (what ros2-client does in `publish`).
//! `RAYON_NUM_THREADS=1 cargo bench -p moma-ros2 --bench convert`

use byteorder::LittleEndian;
use criterion::{Criterion, criterion_group, criterion_main};
use moma_core::{Intrinsics, MetricDepth};
use moma_ros2::convert::{depth_to_cloud, depth_to_image};
use moma_ros2::msg::Header;
use ndarray::Array2;

fn frame() -> (MetricDepth, Intrinsics, image::RgbImage) {
    let depth = MetricDepth::new(Array2::from_shape_fn((480, 640), |(v, u)| {
        if (u * 7 + v * 13) % 97 == 0 {
            f32::NAN
        } else {
            0.6 + 0.0005 * u as f32 + 0.0003 * v as f32
        }
    }));
    let k = Intrinsics {
        width: 640,
        height: 480,
        fx: 600.0,
        fy: 600.0,
        cx: 319.5,
        cy: 239.5,
    };
    let rgb = image::RgbImage::from_fn(640, 480, |u, v| image::Rgb([u as u8, v as u8, 7]));
    (depth, k, rgb)
}

fn bench(c: &mut Criterion) {
    let (depth, k, rgb) = frame();
    let h = Header::default();
    c.bench_function("depth_to_image 640x480", |b| {
        b.iter(|| depth_to_image(&depth, h.clone()))
    });
    c.bench_function("depth_to_cloud xyz 640x480", |b| {
        b.iter(|| depth_to_cloud(&depth, &k, None, h.clone()).unwrap())
    });
    c.bench_function("depth_to_cloud xyzrgb 640x480", |b| {
        b.iter(|| depth_to_cloud(&depth, &k, Some(&rgb), h.clone()).unwrap())
    });
    let img = depth_to_image(&depth, h.clone());
    c.bench_function("cdr encode depth image (1.2 MB)", |b| {
        b.iter(|| cdr_encoding::to_vec::<_, LittleEndian>(&img).unwrap())
    });
    let cloud = depth_to_cloud(&depth, &k, None, h.clone()).unwrap();
    c.bench_function("cdr encode cloud (3.7 MB)", |b| {
        b.iter(|| cdr_encoding::to_vec::<_, LittleEndian>(&cloud).unwrap())
    });
    // ros2-client's publish with no subscriber (nothing is sent): encoding and the writer's
    // admission, what the node pays per message before DDS's own thread takes over. The node is
    // loopback-only: its discovery announcements stay on this machine.
    let mut node =
        moma_ros2::dds::node("bench", "/", 199, moma_ros2::dds::Network::Loopback).unwrap();
    let publ = moma_ros2::dds::publisher::<moma_ros2::msg::PointCloud2>(
        &mut node,
        "bench_points",
        moma_ros2::msg::types::point_cloud2(),
        &moma_ros2::dds::sensor_qos(),
    )
    .unwrap();
    c.bench_function("publish cloud, no subscriber (3.7 MB)", |b| {
        b.iter_batched(
            || cloud.clone(),
            |m| moma_ros2::dds::publish(&publ, m).unwrap(),
            criterion::BatchSize::LargeInput,
        )
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
