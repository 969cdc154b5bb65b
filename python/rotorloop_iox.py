"""Small helpers to take part in a rotorloop loop from Python with iceoryx2's binding:
open a run's domain (its iceoryx2 config, a node named for the role) and its services
with the QoS every rotorloop process opens them with (docs/wire.md, "QoS").

    import rotorloop_iox as rl
    node = rl.open_domain(config_path, domain, "controller")
    states = rl.pubsub(node, domain, "state").subscriber_builder().create()

The sample types are in `rotorloop_wire` (generated from the Rust types).
"""

import iceoryx2 as iox2

import rotorloop_wire as w

# The QoS of docs/wire.md: iceoryx2 refuses a service opened with less.
MAX_PUBLISHERS = 2
MAX_SUBSCRIBERS = 8
MAX_NODES = 16
MAX_BUFFER = 4096
REFERENCE_HISTORY = 32
MAX_NOTIFIERS = 4
MAX_LISTENERS = 8
EVENT_ID_MAX = 8


def open_domain(config_path: str, domain: str, role: str):
    """A node named `rotorloop/<domain>/<role>` in the domain of the iceoryx2 config a
    run wrote (`OUT/config/iceoryx2.toml`, or `$ROTORLOOP_IOX2_CONFIG`)."""
    config = iox2.config.from_file(iox2.FilePath.new(config_path))
    return (
        iox2.NodeBuilder.new()
        .name(iox2.NodeName.new(f"rotorloop/{domain}/{role}"))
        .config(config)
        .create(iox2.ServiceType.Ipc)
    )


def pubsub(node, domain: str, topic: str):
    """The publish-subscribe service of `topic` (`state`, `reference`, `torque`)."""
    return (
        node.service_builder(iox2.ServiceName.new(w.service_name(domain, topic)))
        .publish_subscribe(w.TOPICS[topic])
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .history_size(REFERENCE_HISTORY if topic == "reference" else 1)
        .subscriber_max_buffer_size(MAX_BUFFER)
        .subscriber_max_borrowed_samples(2)
        .enable_safe_overflow(True)
        .open_or_create()
    )


def event(node, domain: str, topic: str):
    """The event service of `topic` (same name): its publisher notifies after each
    sample with event id 0."""
    return (
        node.service_builder(iox2.ServiceName.new(w.service_name(domain, topic)))
        .event()
        .max_notifiers(MAX_NOTIFIERS)
        .max_listeners(MAX_LISTENERS)
        .max_nodes(MAX_NODES)
        .event_id_max_value(EVENT_ID_MAX)
        .open_or_create()
    )
