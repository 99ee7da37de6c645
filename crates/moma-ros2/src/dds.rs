//! The DDS side: a ROS 2 context and node, the QoS profiles moma uses, and typed topics.
//!
//! QoS (docs/ros2.md): sensor data (images, depth, points, grasps, diagnostics) best effort,
//! volatile, keep last 1, the ROS 2 "sensor data" profile a camera driver uses; the node's own
//! subscriptions keep the last [`SENSOR_READER_DEPTH`] samples so that it can count the frames it
//! drops when it is slower than the camera. Calibration (the `calibrate` service) is reliable.

use ros2_client::{
    Context, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher, QosProfile,
    Subscription,
    qos::{Durability, History, WhenFull},
};
use rustdds::DomainParticipantBuilder;
use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::error::{Result, RosError};

/// History depth of the node's sensor subscriptions (bounded: stale frames beyond it are dropped
/// by DDS; those within it are dropped by the node, newest first, and counted).
pub const SENSOR_READER_DEPTH: usize = 4;

/// Where DDS may send.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Network {
    /// Every interface (a robot cell's network).
    #[default]
    All,
    /// Only the loopback interface: multicast and advertised locators on 127.0.0.1, discovery to
    /// the local SPDP ports. Tests run this way, inside a network namespace of their own.
    Loopback,
}

/// The sensor-data profile for publishers: best effort, volatile, keep last 1.
pub fn sensor_qos() -> QosProfile {
    QosProfile::subscription_default()
        .reliability_best_effort()
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 1 })
}

/// The node's sensor subscriptions: best effort, keep last [`SENSOR_READER_DEPTH`].
pub fn sensor_reader_qos() -> QosProfile {
    sensor_qos().history(History::KeepLast {
        depth: SENSOR_READER_DEPTH,
    })
}

/// Reliable, volatile, keep last 10: calibration requests and their replies.
pub fn reliable_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::Wait(std::time::Duration::from_millis(500)))
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 })
}

fn dds(e: impl std::fmt::Debug) -> RosError {
    RosError::Dds(format!("{e:?}"))
}

/// A ROS 2 node on `domain_id` named `name` in the namespace `namespace` (`/`: the root).
///
/// # Errors
/// DDS could not start (ports in use, no interface) or the name is not a ROS 2 name.
pub fn node(name: &str, namespace: &str, domain_id: u16, network: Network) -> Result<Node> {
    let mut builder = DomainParticipantBuilder::new(domain_id);
    if network == Network::Loopback {
        builder = builder.with_only_networks([std::net::Ipv4Addr::LOCALHOST]);
    }
    let participant = builder.build().map_err(dds)?;
    let context = Context::from_domain_participant(participant).map_err(dds)?;
    let node_name = NodeName::new(namespace, name).map_err(|e| RosError::Name {
        name: format!("{namespace} {name}"),
        why: format!("{e:?}"),
    })?;
    context
        .new_node(node_name, NodeOptions::new().enable_rosout(false))
        .map_err(dds)
}

/// A topic name: absolute (`/camera/image`) or relative to the node's namespace (`image`).
///
/// # Errors
/// Not a ROS 2 name.
pub fn topic_name(name: &str) -> Result<Name> {
    let parsed = if name.starts_with('/') {
        Name::parse(name)
    } else {
        Name::parse(&format!("/{name}"))
    };
    parsed.map_err(|e| RosError::Name {
        name: name.to_string(),
        why: name_error(name, &e),
    })
}

/// Why a topic name was refused, in moma's words (ros2-client's own messages are misspelt,
/// its `Debug` names are Rust's, and the character it reports is not always the one in the
/// name).
fn name_error(name: &str, e: &ros2_client::names::NameError) -> String {
    match e {
        ros2_client::names::NameError::Empty => "a topic name cannot be empty".to_string(),
        ros2_client::names::NameError::BadChar(reported) => {
            // the characters are allowed, their places are not
            if name
                .split('/')
                .any(|part| part.starts_with(|c: char| c.is_ascii_digit()))
            {
                return "a part of a topic name cannot start with a digit".to_string();
            }
            if name.contains("__") {
                return "a topic name cannot hold '__' (two underscores)".to_string();
            }
            let c = name
                .chars()
                .find(|c| !(c.is_ascii_alphanumeric() || *c == '_' || *c == '/'))
                .unwrap_or(*reported);
            let hint = match c {
                '~' => {
                    " ('~', the node's private namespace, is not expanded: give the full \
                        name, e.g. /moma/depth)"
                }
                ' ' => " (a space)",
                _ => "",
            };
            format!(
                "{c:?} is not allowed in a topic name (letters, digits, '_' and '/' \
                 separators){hint}"
            )
        }
        ros2_client::names::NameError::BadSlash(..) => {
            "a '/' separator is misplaced (no empty part, no trailing '/')".to_string()
        }
    }
}

/// A publisher of `M` on topic `name` with type `type_name`.
///
/// # Errors
/// A bad name; DDS refused.
pub fn publisher<M: Serialize>(
    node: &mut Node,
    name: &str,
    type_name: MessageTypeName,
    qos: &QosProfile,
) -> Result<Publisher<M>> {
    let topic = node
        .create_topic(&topic_name(name)?, type_name, qos)
        .map_err(dds)?;
    node.create_publisher(&topic, Some(qos.clone()))
        .map_err(dds)
}

/// A subscription to `M` on topic `name` with type `type_name`.
///
/// # Errors
/// A bad name; DDS refused.
pub fn subscription<M: 'static + DeserializeOwned>(
    node: &mut Node,
    name: &str,
    type_name: MessageTypeName,
    qos: &QosProfile,
) -> Result<Subscription<M>> {
    let topic = node
        .create_topic(&topic_name(name)?, type_name, qos)
        .map_err(dds)?;
    node.create_subscription(&topic, Some(qos.clone()))
        .map_err(dds)
}

/// Publishes `message`; a failure is returned as text (the caller reports it in diagnostics:
/// a best-effort publish only fails when DDS is shutting down).
///
/// # Errors
/// DDS refused the sample.
pub fn publish<M: Serialize>(publisher: &Publisher<M>, message: M) -> Result<()> {
    // The error carries the sample back; only its description is kept.
    publisher
        .publish(message)
        .map_err(|e| RosError::Dds(e.to_string()))
}

/// The `calibrate` service's server (`std_srvs/srv/Trigger`, reliable, the ROS 2 default
/// request/reply mapping).
///
/// # Errors
/// A bad name; DDS refused.
pub fn trigger_server(
    node: &mut Node,
    name: &str,
) -> Result<ros2_client::Server<crate::msg::TriggerRequest, crate::msg::TriggerResponse>> {
    node.create_server(
        ros2_client::ServiceMapping::Enhanced,
        &topic_name(name)?,
        &crate::msg::types::trigger(),
        reliable_qos(),
        reliable_qos(),
    )
    .map_err(dds)
}

/// A client of a `std_srvs/srv/Trigger` service (tests, tools).
///
/// # Errors
/// A bad name; DDS refused.
pub fn trigger_client(
    node: &mut Node,
    name: &str,
) -> Result<ros2_client::Client<crate::msg::TriggerRequest, crate::msg::TriggerResponse>> {
    node.create_client(
        ros2_client::ServiceMapping::Enhanced,
        &topic_name(name)?,
        &crate::msg::types::trigger(),
        reliable_qos(),
        reliable_qos(),
    )
    .map_err(dds)
}
