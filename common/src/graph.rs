//! The loop's graph as data: its four roles, its three topics, and one table of who
//! publishes and who subscribes each topic ([`GRAPH`]), in the spirit of copper-rs's
//! `cnx` list. What depends on the wiring derives from it: the plant's subscriber count,
//! which topics a split run bridges between hosts, the launcher's start order, and the
//! order `ps` lists roles in.
//!
//! A role's name (`plant`, …) is what the CLI parses and the output files write; inside
//! the code a role is a [`Role`].

use std::fmt;
use std::str::FromStr;

/// A process of the loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Role {
    /// Simulates the body with rotors on the absolute time grid; publishes the state.
    Plant,
    /// Generates the desired attitude from a dummy body; publishes the reference.
    Reference,
    /// Runs the law; publishes the rotor torques.
    Controller,
    /// Subscribes to everything and records; publishes nothing.
    Monitor,
}

/// A topic of the loop: a publish-subscribe service and an event service of the same
/// name (the publisher notifies after each send).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Topic {
    /// [`crate::wire::StateSample`], from the plant.
    State,
    /// [`crate::wire::ReferenceSample`], from the reference.
    Reference,
    /// [`crate::wire::TorqueSample`], from the controller.
    Torque,
}

/// One topic's connection: its publisher and its subscribers.
#[derive(Debug, Clone, Copy)]
pub struct Connection {
    /// The topic.
    pub topic: Topic,
    /// The one role that publishes it.
    pub publisher: Role,
    /// The roles that subscribe to it.
    pub subscribers: &'static [Role],
}

/// The loop: every topic, who publishes it and who reads it.
pub const GRAPH: [Connection; 3] = [
    Connection {
        topic: Topic::State,
        publisher: Role::Plant,
        subscribers: &[Role::Reference, Role::Controller, Role::Monitor],
    },
    Connection {
        topic: Topic::Reference,
        publisher: Role::Reference,
        subscribers: &[Role::Controller, Role::Monitor],
    },
    Connection {
        topic: Topic::Torque,
        publisher: Role::Controller,
        subscribers: &[Role::Plant, Role::Monitor],
    },
];

impl Role {
    /// Every role, in the launcher's start order: the roles that only read first (the
    /// monitor, so it sees tick 0), then each publisher after the readers of its topic
    /// that do not close a cycle with it, and the plant last, because its first state
    /// starts the clock that everyone else follows.
    pub const ALL: [Role; 4] = start_order();

    /// The role's name, as the CLI takes it and the output files write it.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Plant => "plant",
            Self::Reference => "reference",
            Self::Controller => "controller",
            Self::Monitor => "monitor",
        }
    }

    /// The topic the role publishes, if any.
    pub fn publishes(self) -> Option<Topic> {
        GRAPH.iter().find(|c| c.publisher == self).map(|c| c.topic)
    }

    /// The topics the role subscribes to.
    pub fn subscribes(self) -> impl Iterator<Item = Topic> {
        GRAPH.iter().filter(move |c| c.subscribers.contains(&self)).map(|c| c.topic)
    }

    /// Whether the role publishes or subscribes to `topic`.
    pub fn uses(self, topic: Topic) -> bool {
        self.publishes() == Some(topic) || self.subscribes().any(|t| t == topic)
    }
}

/// The start order from [`GRAPH`]: ascending by how many roles read the role's topic
/// (the monitor 0, the reference 2, the controller 2, the plant 3), ties broken by the
/// graph, a publisher before the roles that read it.
const fn start_order() -> [Role; 4] {
    let mut order = [Role::Monitor, Role::Reference, Role::Controller, Role::Plant];
    // Insertion sort, as a const fn can do it.
    let mut i = 1;
    while i < order.len() {
        let mut j = i;
        while j > 0 && starts_before(order[j], order[j - 1]) {
            let t = order[j];
            order[j] = order[j - 1];
            order[j - 1] = t;
            j -= 1;
        }
        i += 1;
    }
    order
}

/// How many roles read `role`'s topic (0 for a role that publishes nothing).
const fn readers(role: Role) -> usize {
    let mut i = 0;
    while i < GRAPH.len() {
        if GRAPH[i].publisher as u8 == role as u8 {
            return GRAPH[i].subscribers.len();
        }
        i += 1;
    }
    0
}

/// Whether `a` reads `b`'s topic.
const fn reads(a: Role, b: Role) -> bool {
    let mut i = 0;
    while i < GRAPH.len() {
        if GRAPH[i].publisher as u8 == b as u8 {
            let s = GRAPH[i].subscribers;
            let mut j = 0;
            while j < s.len() {
                if s[j] as u8 == a as u8 {
                    return true;
                }
                j += 1;
            }
        }
        i += 1;
    }
    false
}

const fn starts_before(a: Role, b: Role) -> bool {
    let (ra, rb) = (readers(a), readers(b));
    ra < rb || ra == rb && reads(b, a)
}

impl Topic {
    /// Every topic.
    pub const ALL: [Topic; 3] = [Topic::State, Topic::Reference, Topic::Torque];

    /// The topic's service name under the domain (`state`, `reference`, `torque`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::State => "state",
            Self::Reference => "reference",
            Self::Torque => "torque",
        }
    }

    /// The one role that publishes it.
    pub fn publisher(self) -> Role {
        self.connection().publisher
    }

    /// The roles that subscribe to it.
    pub fn subscribers(self) -> &'static [Role] {
        self.connection().subscribers
    }

    fn connection(self) -> &'static Connection {
        GRAPH.iter().find(|c| c.topic == self).expect("every topic is in the graph")
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is not a role.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NotARole(pub String);

impl fmt::Display for NotARole {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "`{}` is not a role: plant, reference, controller or monitor", self.0)
    }
}

impl std::error::Error for NotARole {}

impl FromStr for Role {
    type Err = NotARole;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Role::ALL.into_iter().find(|r| r.name() == s).ok_or_else(|| NotARole(s.to_owned()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_start_order_follows_from_the_graph() {
        // The order the launcher has always used: monitor first, plant last.
        assert_eq!(Role::ALL, [Role::Monitor, Role::Reference, Role::Controller, Role::Plant]);
    }

    #[test]
    fn every_topic_has_one_publisher_and_every_role_is_wired() {
        for t in Topic::ALL {
            assert_eq!(GRAPH.iter().filter(|c| c.topic == t).count(), 1, "{t:?}");
            assert!(!t.subscribers().contains(&t.publisher()), "{t:?} reads itself");
        }
        assert_eq!(Role::Monitor.publishes(), None);
        assert_eq!(Role::Monitor.subscribes().count(), 3, "the monitor reads everything");
        assert_eq!(Topic::State.subscribers().len(), 3);
        assert!(Role::Controller.uses(Topic::Reference) && !Role::Plant.uses(Topic::Reference));
        for r in Role::ALL {
            assert_eq!(r.name().parse::<Role>(), Ok(r));
        }
        let e = "pilot".parse::<Role>().expect_err("not a role").to_string();
        assert!(e.contains("pilot") && e.contains("plant, reference, controller or monitor"));
    }
}
