//! # moma-ros2
//!
//! ROS 2 for moma without a ROS installation: the messages the node speaks (`msg`, CDR-encoded by
//! ros2-client exactly as `rmw` does), checked conversions to and from moma's types (`convert`),
//! and the DDS side (`dds`: nodes, QoS profiles, typed topics) over ros2-client and RustDDS.
//!
//! The node itself (`moma ros2`) and the camera replay (`moma ros2-replay`) live in the `moma`
//! binary, which adds the depth model and the file formats; docs/ros2.md describes the topics.
//!
//! Frames follow REP 103/105's optical convention: x right, y down, z forward, metres.

pub mod convert;
pub mod dds;
pub mod error;
pub mod msg;

pub use error::{Result, RosError};
