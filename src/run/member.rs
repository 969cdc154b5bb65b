//! A process the launcher starts, supervises and can fault: one of the loop's roles, or
//! with `--split` the link gateway of a host. Parsed once where the command line names one
//! (`--fault`); written as the name the files use (`plant`, `link-b`).

use rotorloop_common::graph::Role;

/// A process of a run: a role, or a gateway of a split run.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Member {
    /// One of the loop's four roles.
    Role(Role),
    /// The link gateway of this host (`link-HOST`).
    Gateway(String),
}

impl Member {
    /// The role, if it is one.
    pub fn role(&self) -> Option<Role> {
        match self {
            Self::Role(r) => Some(*r),
            Self::Gateway(_) => None,
        }
    }

    /// Whether it is the role `r`.
    pub fn is(&self, r: Role) -> bool {
        self.role() == Some(r)
    }
}

impl From<Role> for Member {
    fn from(r: Role) -> Self {
        Self::Role(r)
    }
}

impl std::fmt::Display for Member {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Role(r) => f.write_str(r.name()),
            Self::Gateway(host) => write!(f, "link-{host}"),
        }
    }
}

impl std::str::FromStr for Member {
    type Err = String;

    /// `plant`, `reference`, `controller`, `monitor` or `link-HOST`.
    fn from_str(s: &str) -> Result<Self, String> {
        match s.strip_prefix("link-") {
            Some(host) if !host.is_empty() => Ok(Self::Gateway(host.to_owned())),
            _ => s.parse::<Role>().map(Self::Role).map_err(|_| {
                format!(
                    "`{s}` is plant, reference, controller, monitor or (with --split) link-HOST"
                )
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_member_reads_back_what_it_writes() {
        for m in [Member::Role(Role::Controller), Member::Gateway("b".into())] {
            assert_eq!(m.to_string().parse::<Member>(), Ok(m));
        }
        assert!("link-".parse::<Member>().is_err());
        assert!("pilot".parse::<Member>().is_err());
        assert!(Member::from(Role::Plant).is(Role::Plant));
    }
}
