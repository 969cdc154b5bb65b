//! The QoS every service of a run is opened with, and the domain configuration's defaults
//! that make a link gateway's mirrors openable with it.

use iceoryx2::prelude::*;

use super::MAX_BUFFER;
use crate::graph::Topic;
use crate::wire::REFERENCE_LEAD;

/// History kept for late subscribers: the reference keeps its whole lead.
pub(crate) fn history(topic: Topic) -> usize {
    match topic {
        Topic::Reference => 2 * REFERENCE_LEAD as usize,
        _ => 1,
    }
}

/// The QoS every publish-subscribe service of a run is opened with. Two publishers: the
/// role's and, when the topic crosses hosts, the link gateway's (a second role of the same
/// kind is refused by [`Domain::node`], not by the service).
pub(crate) struct PubSubQos {
    pub(crate) max_publishers: usize,
    pub(crate) max_subscribers: usize,
    pub(crate) max_nodes: usize,
    pub(crate) subscriber_max_buffer_size: usize,
    pub(crate) subscriber_max_borrowed_samples: usize,
    pub(crate) enable_safe_overflow: bool,
}

pub(crate) const PUBSUB_QOS: PubSubQos = PubSubQos {
    max_publishers: 2,
    max_subscribers: 8,
    max_nodes: 16,
    subscriber_max_buffer_size: MAX_BUFFER,
    subscriber_max_borrowed_samples: 2,
    enable_safe_overflow: true,
};

/// The QoS of every event service of a run.
pub(crate) struct EventQos {
    pub(crate) max_notifiers: usize,
    pub(crate) max_listeners: usize,
    pub(crate) max_nodes: usize,
    pub(crate) event_id_max_value: usize,
}

pub(crate) const EVENT_QOS: EventQos =
    EventQos { max_notifiers: 4, max_listeners: 8, max_nodes: 16, event_id_max_value: 8 };

/// A link gateway creates the mirror of a remote service with the local configuration's
/// defaults (iceoryx2-link 0.10), and a role then opens it with the QoS above, which
/// iceoryx2 checks as minimums. So the defaults of a domain's configuration are that QoS,
/// with the largest history of any topic: whoever creates a service first, every role
/// can open it.
pub(crate) fn set_mirror_defaults(config: &mut Config) {
    let ps = &mut config.defaults.publish_subscribe;
    ps.max_publishers = PUBSUB_QOS.max_publishers;
    ps.max_subscribers = PUBSUB_QOS.max_subscribers;
    ps.max_nodes = PUBSUB_QOS.max_nodes;
    ps.subscriber_max_buffer_size = PUBSUB_QOS.subscriber_max_buffer_size;
    ps.subscriber_max_borrowed_samples = PUBSUB_QOS.subscriber_max_borrowed_samples;
    ps.enable_safe_overflow = PUBSUB_QOS.enable_safe_overflow;
    ps.publisher_history_size = history(Topic::Reference);
    let ev = &mut config.defaults.event;
    ev.max_notifiers = EVENT_QOS.max_notifiers;
    ev.max_listeners = EVENT_QOS.max_listeners;
    ev.max_nodes = EVENT_QOS.max_nodes;
    ev.event_id_max_value = EVENT_QOS.event_id_max_value;
}
