//! The listening gateway proves to the connecting one that it is the run's (issue 62,
//! point 5). Zenoh's user/password authentication is one way: the listener checks the
//! connecting side, never the other way round, so whoever holds the port when the
//! connecting gateway dials (before the listener binds it, or while a killed listener is
//! down) would receive what crosses and could send samples into the loop.
//!
//! So a connecting gateway with credentials carries nothing to or from a peer before
//! that peer proved it knows the run's password: it asks, on `rotorloop-link-proof/<D>`,
//! with a fresh 32-byte nonce from the kernel, its user and its own Zenoh id; the
//! listener answers with its Zenoh id and `HMAC-SHA256(password, CONTEXT ‖ D ‖ user ‖
//! nonce ‖ listener id ‖ connector id)`, the password being the user's in its users
//! file. The connecting gateway accepts a peer once an answer names it and its MAC is
//! right. Every transport that opens or closes (a redial after the listener was killed)
//! makes it ask again before the next pass, and a peer that gives no right answer within
//! [`PROOF_WAIT`] stops the gateway (exit 1, naming the peer): it fails closed, and the
//! launcher's policy decides what follows. The nonce makes an old answer useless; the
//! ids bind the answer to the two ends of this session as each declares itself (Zenoh
//! ids are not proven: a relay of both handshakes is not caught, docs/security.md).

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use hmac::{Hmac, Mac};
use sha2::Sha256;
use zenoh::Wait;
use zenoh::query::{ConsolidationMode, Query, QueryTarget};
use zenoh::sample::Locality;

use rotorloop_common::private::hex;

use crate::config::{TestProof, config_string};

/// What the MAC covers first: an answer here is nothing else's (Zenoh's own handshake MAC
/// is keyed by its nonce, over the password; this one is keyed by the password).
const CONTEXT: &[u8] = b"rotorloop-link listener proof 1\0";

/// How long a connecting gateway waits for a new peer's proof before it stops. The
/// listener's queryable is declared before it listens, and its declaration reaches the
/// peer with the session's first messages (within milliseconds on loopback); the rest is
/// room for a loaded machine.
pub const PROOF_WAIT: Duration = Duration::from_secs(10);

/// How often the question is asked again while no right answer came.
const ASK_EVERY: Duration = Duration::from_millis(50);

/// The key of a domain's proofs.
fn key(domain: &str) -> String {
    format!("rotorloop-link-proof/{domain}")
}

/// The MAC of an answer to `user`'s question.
fn mac(
    password: &str,
    [domain, user]: [&str; 2],
    nonce: &[u8],
    listener: &str,
    connector: &str,
) -> Vec<u8> {
    let mut m = Hmac::<Sha256>::new_from_slice(password.as_bytes()).expect("any key length");
    let parts = [CONTEXT, domain.as_bytes(), user.as_bytes(), nonce];
    for part in parts.into_iter().chain([listener.as_bytes(), connector.as_bytes()]) {
        m.update(&(part.len() as u64).to_le_bytes());
        m.update(part);
    }
    m.finalize().into_bytes().to_vec()
}

fn unhex(s: &str) -> Option<Vec<u8>> {
    if s.len() % 2 != 0 {
        return None;
    }
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok()).collect()
}

/// A string field of a JSON object.
fn field<'a>(v: &'a serde_json::Value, name: &str) -> Option<&'a str> {
    v.get(name)?.as_str()
}

/// The users of a users file, read as Zenoh reads it: `user:password` lines, each line,
/// user and password trimmed, empty lines skipped.
fn users(path: &str) -> anyhow::Result<HashMap<String, String>> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| anyhow::anyhow!("cannot read the users file {path}: {e}"))?;
    Ok(text
        .lines()
        .filter_map(|l| l.trim().split_once(':'))
        .map(|(u, p)| (u.trim().to_owned(), p.trim().to_owned()))
        .filter(|(u, p)| !u.is_empty() && !p.is_empty())
        .collect())
}

/// The listening side: answers every question about the run's users, for as long as it
/// is kept. `None` where the session has no users file (it does not check its peers, so
/// it has nothing to prove with).
pub struct Answerer {
    _queryable: zenoh::query::Queryable<()>,
}

impl Answerer {
    /// Declares the answer of a listening gateway of `domain` (before it listens: the
    /// session is opened with its endpoints, so this comes right after).
    /// `test` plays a peer that cannot prove it (see [`TestProof`]).
    pub fn open(
        session: &zenoh::Session,
        config: &zenoh::Config,
        domain: &str,
        test: Option<TestProof>,
    ) -> anyhow::Result<Option<Self>> {
        let Some(path) = config_string(config, "transport/auth/usrpwd/dictionary_file") else {
            return Ok(None);
        };
        let mut users = users(&path)?;
        match test {
            Some(TestProof::Silent) => return Ok(None),
            Some(TestProof::Wrong) => users.values_mut().for_each(|p| p.push('x')),
            None => {}
        }
        let (own, domain) = (session.zid().to_string(), domain.to_owned());
        let queryable = session
            .declare_queryable(key(&domain))
            .allowed_origin(Locality::Remote)
            .callback(move |q: Query| {
                if let Some(answer) = answer(&q, &users, &domain, &own) {
                    let _ = q.reply(q.key_expr().clone(), answer).wait();
                }
            })
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot declare the listener's proof: {e}"))?;
        Ok(Some(Self { _queryable: queryable }))
    }
}

/// The answer to question `q`, or none (an unknown user or a malformed question).
fn answer(q: &Query, users: &HashMap<String, String>, domain: &str, own: &str) -> Option<String> {
    let asked: serde_json::Value = serde_json::from_slice(&q.payload()?.to_bytes()).ok()?;
    let user = field(&asked, "user")?;
    let password = users.get(user)?;
    let nonce = unhex(field(&asked, "nonce")?).filter(|n| n.len() == 32)?;
    let connector = field(&asked, "connector")?;
    let m = mac(password, [domain, user], &nonce, own, connector);
    Some(serde_json::json!({ "listener": own, "mac": hex(&m) }).to_string())
}

impl std::fmt::Debug for Answerer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Answerer")
    }
}

/// A peer that did not prove it is the run's listening gateway.
#[derive(Debug, thiserror::Error)]
#[error(
    "the peer {peer} did not prove within {} s that it is the run's listening gateway \
     (no answer with the run's password: another process may hold the port); stopping, so \
     that nothing crosses to it",
    PROOF_WAIT.as_secs()
)]
pub struct Unproven {
    /// The peer's Zenoh id.
    pub peer: String,
}

/// The connecting side: carries nothing before every peer proved it is the run's
/// listener, and asks again whenever a transport opened or closed since.
///
/// A pass of the link runs under [`Gate::hold`]'s guard, and the transport events take
/// the same lock before they count: a transport that opens during a pass waits (its
/// routing face is made after the event, so nothing reaches it or comes from it) until the
/// pass ends, and the next pass asks first.
pub struct Gate {
    user: String,
    password: String,
    domain: String,
    /// How many transports opened or closed (counted under the lock passes hold).
    changes: Arc<Mutex<u64>>,
    /// The count of changes when the peers were last proven.
    proven: Option<u64>,
    /// How many times peers were proven.
    proofs: u64,
    _events: zenoh::session::TransportEventsListener<()>,
}

impl Gate {
    /// The gate of a connecting gateway of `domain`; `None` where the session has no
    /// user and password (a listener only, or a `--zenoh` file with mutual TLS, which
    /// proves both ends itself).
    pub fn open(
        session: &zenoh::Session,
        config: &zenoh::Config,
        domain: &str,
    ) -> anyhow::Result<Option<Self>> {
        let user = config_string(config, "transport/auth/usrpwd/user");
        let password = config_string(config, "transport/auth/usrpwd/password");
        let (Some(user), Some(password)) = (user, password) else { return Ok(None) };
        let changes = Arc::new(Mutex::new(1));
        let count = Arc::clone(&changes);
        // Called as the transport is made, before its routing face (what routes samples
        // to and from it): waits for a pass under way to end.
        let events = session
            .info()
            .transport_events_listener()
            .callback(move |_| *lock(&count) += 1)
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot watch the session's transports: {e}"))?;
        Ok(Some(Self {
            user,
            password,
            domain: domain.to_owned(),
            changes,
            proven: None,
            proofs: 0,
            _events: events,
        }))
    }

    /// Holds the gate open for one pass of the link: `Some(guard)` once the transports
    /// are as they were when they were last proven, or are proven now (waiting at most
    /// [`PROOF_WAIT`] for a new one's answer); `None` without a transport, or when one came
    /// while they were being proven (the next call asks again). An error for a transport
    /// that gave no right answer.
    pub fn hold(
        &mut self,
        session: &zenoh::Session,
    ) -> Result<Option<MutexGuard<'_, u64>>, Unproven> {
        let changes = *lock(&self.changes);
        if self.proven != Some(changes) {
            if !self.prove(session)? {
                return Ok(None);
            }
            self.proven = Some(changes);
            self.proofs += 1;
        }
        let guard = lock(&self.changes);
        Ok((self.proven == Some(*guard)).then_some(guard))
    }

    /// Asks every transport (peer, router or client alike) until each gave a right
    /// answer; the set is read again each round (one that closed is not waited for).
    /// `Ok(false)` without a transport.
    fn prove(&self, session: &zenoh::Session) -> Result<bool, Unproven> {
        let deadline = Instant::now() + PROOF_WAIT;
        let mut proven = Vec::new();
        loop {
            let now: Vec<String> =
                session.info().transports().wait().map(|t| t.zid().to_string()).collect();
            if now.is_empty() {
                return Ok(false);
            }
            let mut unproven: Vec<String> =
                now.into_iter().filter(|z| !proven.contains(z)).collect();
            if unproven.is_empty() {
                return Ok(true);
            }
            if Instant::now() >= deadline {
                return Err(Unproven { peer: unproven.swap_remove(0) });
            }
            proven.extend(self.ask(session, &unproven));
            if !unproven.iter().all(|z| proven.contains(z)) {
                std::thread::sleep(ASK_EVERY);
            }
        }
    }

    /// How many times peers were proven (once at the start, again after each redial).
    pub fn proofs(&self) -> u64 {
        self.proofs
    }

    /// Asks once: the transports of `asked` that gave a right answer.
    fn ask(&self, session: &zenoh::Session, asked: &[String]) -> Vec<String> {
        let Ok(nonce) = rotorloop_common::private::random_bytes::<32>() else { return Vec::new() };
        let own = session.zid().to_string();
        let question =
            serde_json::json!({ "user": self.user, "nonce": hex(&nonce), "connector": own });
        // Every answer, from every queryable (one that says it is complete takes none
        // from the others, and answers on one key are not merged into one).
        let Ok(replies) = session
            .get(key(&self.domain))
            .payload(question.to_string())
            .allowed_destination(Locality::Remote)
            .target(QueryTarget::All)
            .consolidation(ConsolidationMode::None)
            .timeout(ASK_EVERY * 4)
            .wait()
        else {
            return Vec::new();
        };
        let mut right = Vec::new();
        while let Ok(reply) = replies.recv() {
            let Ok(sample) = reply.result() else { continue };
            let Ok(said) =
                serde_json::from_slice::<serde_json::Value>(&sample.payload().to_bytes())
            else {
                continue;
            };
            let (Some(listener), Some(got)) = (field(&said, "listener"), field(&said, "mac"))
            else {
                continue;
            };
            let want = mac(&self.password, [&self.domain, &self.user], &nonce, listener, &own);
            if asked.iter().any(|a| a == listener)
                && unhex(got).is_some_and(|g| constant_time_eq(&g, &want))
            {
                right.push(listener.to_owned());
            }
        }
        right
    }
}

/// The count's lock, whatever a panic elsewhere left in it (a count has no invariant).
fn lock(m: &Mutex<u64>) -> MutexGuard<'_, u64> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl std::fmt::Debug for Gate {
    /// The user and the state, never the password.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gate")
            .field("user", &self.user)
            .field("domain", &self.domain)
            .field("proven", &self.proven)
            .field("proofs", &self.proofs)
            .finish_non_exhaustive()
    }
}

/// Equality without an early exit on the first differing byte.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The MAC binds every part: the password, the domain, the user, the nonce and both
    /// ids.
    #[test]
    fn the_mac_changes_with_every_part() {
        let base = mac("pw", ["d", "u"], &[1; 32], "L", "C");
        assert_eq!(base, mac("pw", ["d", "u"], &[1; 32], "L", "C"));
        for other in [
            mac("pX", ["d", "u"], &[1; 32], "L", "C"),
            mac("pw", ["e", "u"], &[1; 32], "L", "C"),
            mac("pw", ["d", "v"], &[1; 32], "L", "C"),
            mac("pw", ["d", "u"], &[2; 32], "L", "C"),
            mac("pw", ["d", "u"], &[1; 32], "S", "C"),
            mac("pw", ["d", "u"], &[1; 32], "L", "D"),
            // Lengths are part of it: moving a byte between parts is another message.
            mac("pw", ["du", ""], &[1; 32], "L", "C"),
        ] {
            assert_ne!(base, other);
        }
    }

    /// The users file is read as Zenoh reads it (lines, users and passwords trimmed), so a
    /// listener Zenoh lets a peer in with can answer that peer.
    #[test]
    fn the_users_file_is_read_as_zenoh_reads_it() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("users");
        std::fs::write(&path, "  rotorloop : s3cret \n\nbad line\nother:a:b\n:nouser\nnopass:\n")
            .expect("write");
        let u = users(path.to_str().expect("utf8")).expect("read");
        assert_eq!(u.get("rotorloop").map(String::as_str), Some("s3cret"));
        assert_eq!(u.get("other").map(String::as_str), Some("a:b"));
        assert_eq!(u.len(), 2, "{u:?}");
    }

    #[test]
    fn hex_round_trips_and_refuses_what_is_not_hex() {
        assert_eq!(unhex(&hex(&[0, 15, 255])), Some(vec![0, 15, 255]));
        assert_eq!(unhex("abc"), None);
        assert_eq!(unhex("zz"), None);
        assert!(constant_time_eq(b"ab", b"ab"));
        assert!(!constant_time_eq(b"ab", b"ac"));
        assert!(!constant_time_eq(b"ab", b"abc"));
    }
}
