//! The listening gateway proves to the connecting one that it is the run's (issue 62,
//! point 5). Zenoh's user/password authentication is one way: the listener checks the
//! connecting side, never the other way round, so whoever holds the port when the
//! connecting gateway dials (before the listener binds it, or while a killed listener is
//! down) would receive what crosses and could send samples into the loop.
//!
//! So a connecting gateway with credentials carries nothing to or from a peer before
//! that peer proved it knows the run's password: it asks, on `rotorloop-link-proof/<D>`,
//! with a fresh 32-byte nonce from the kernel, its user and its own Zenoh id; the
//! listener answers with its Zenoh id and `HMAC-SHA256(password, CONTEXT ‖ D ‖ nonce ‖
//! listener id ‖ connector id)`, the password being the user's in its users file. The
//! connecting gateway accepts a peer once an answer names it and its MAC is right. Every
//! transport that opens or closes (a redial after the listener was killed) makes it ask
//! again before the next pass, and a peer that gives no right answer within
//! [`PROOF_WAIT`] stops the gateway (exit 1, naming the peer): it fails closed, and the
//! launcher's policy decides what follows. The nonce makes an old answer useless; the
//! ids bind the answer to the two ends of this session (one relayed from elsewhere names
//! another listener than the peer).

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use hmac::{Hmac, Mac};
use sha2::Sha256;
use zenoh::Wait;
use zenoh::query::Query;
use zenoh::sample::Locality;

use crate::config::TestProof;

/// What the MAC covers first: an answer here is nothing else's (Zenoh's own handshake MAC
/// is over its nonce alone).
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

/// The MAC of an answer.
fn mac(password: &str, domain: &str, nonce: &[u8], listener: &str, connector: &str) -> Vec<u8> {
    let mut m = Hmac::<Sha256>::new_from_slice(password.as_bytes()).expect("any key length");
    for part in [CONTEXT, domain.as_bytes(), nonce, listener.as_bytes(), connector.as_bytes()] {
        m.update(&(part.len() as u64).to_le_bytes());
        m.update(part);
    }
    m.finalize().into_bytes().to_vec()
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
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

/// A JSON string value of the Zenoh configuration at `key`, if set and not empty.
fn config_string(config: &zenoh::Config, key: &str) -> Option<String> {
    let v: serde_json::Value = serde_json::from_str(&config.get_json(key).ok()?).ok()?;
    v.as_str().filter(|s| !s.is_empty()).map(String::from)
}

/// The users of a users file (`user:password` lines, as Zenoh reads it).
fn users(path: &str) -> anyhow::Result<HashMap<String, String>> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| anyhow::anyhow!("cannot read the users file {path}: {e}"))?;
    Ok(text
        .lines()
        .filter_map(|l| l.split_once(':'))
        .map(|(u, p)| (u.to_owned(), p.to_owned()))
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
    let password = users.get(field(&asked, "user")?)?;
    let nonce = unhex(field(&asked, "nonce")?).filter(|n| n.len() == 32)?;
    let connector = field(&asked, "connector")?;
    let m = mac(password, domain, &nonce, own, connector);
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
pub struct Gate {
    user: String,
    password: String,
    domain: String,
    /// Bumped by every transport that opens or closes.
    changes: Arc<AtomicU64>,
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
        let changes = Arc::new(AtomicU64::new(1));
        let bump = Arc::clone(&changes);
        // Called as the transport is made, before any of the peer's declarations are
        // taken: no pass after this reaches a new peer unasked.
        let events = session
            .info()
            .transport_events_listener()
            .callback(move |_| {
                bump.fetch_add(1, Ordering::SeqCst);
            })
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

    /// Whether the gateway may carry samples now: the peers are as they were when they
    /// were last proven, or they are proven now (waiting at most [`PROOF_WAIT`] for a new
    /// peer's proof). `Ok(false)` without a peer; an error for a peer that gave no proof.
    pub fn open_now(&mut self, session: &zenoh::Session) -> Result<bool, Unproven> {
        let changes = self.changes.load(Ordering::SeqCst);
        if self.proven == Some(changes) {
            return Ok(true);
        }
        let peers: Vec<String> = session.info().peers_zid().wait().map(|z| z.to_string()).collect();
        if peers.is_empty() {
            return Ok(false);
        }
        let deadline = Instant::now() + PROOF_WAIT;
        let mut unproven = peers.clone();
        while !unproven.is_empty() {
            self.ask(session, &mut unproven);
            if unproven.is_empty() || Instant::now() >= deadline {
                break;
            }
            std::thread::sleep(ASK_EVERY);
        }
        if let Some(peer) = unproven.into_iter().next() {
            return Err(Unproven { peer });
        }
        // Proven as of `changes`: a transport that came meanwhile is asked about next pass.
        self.proven = Some(changes);
        self.proofs += 1;
        Ok(true)
    }

    /// How many times peers were proven (once at the start, again after each redial).
    pub fn proofs(&self) -> u64 {
        self.proofs
    }

    /// Asks once, and removes from `unproven` each peer whose answer is right.
    fn ask(&self, session: &zenoh::Session, unproven: &mut Vec<String>) {
        let Ok(nonce) = rotorloop_common::private::random_bytes::<32>() else { return };
        let own = session.zid().to_string();
        let question =
            serde_json::json!({ "user": self.user, "nonce": hex(&nonce), "connector": own });
        let Ok(replies) = session
            .get(key(&self.domain))
            .payload(question.to_string())
            .allowed_destination(Locality::Remote)
            .timeout(ASK_EVERY * 4)
            .wait()
        else {
            return;
        };
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
            let want = mac(&self.password, &self.domain, &nonce, listener, &own);
            if unhex(got).is_some_and(|g| constant_time_eq(&g, &want)) {
                unproven.retain(|p| p != listener);
            }
        }
    }
}

impl std::fmt::Debug for Gate {
    /// The user and the state, never the password.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gate")
            .field("user", &self.user)
            .field("domain", &self.domain)
            .field("proven", &self.proven)
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

    /// The MAC binds every part: the password, the domain, the nonce and both ids.
    #[test]
    fn the_mac_changes_with_every_part() {
        let base = mac("pw", "d", &[1; 32], "L", "C");
        assert_eq!(base, mac("pw", "d", &[1; 32], "L", "C"));
        for other in [
            mac("pX", "d", &[1; 32], "L", "C"),
            mac("pw", "e", &[1; 32], "L", "C"),
            mac("pw", "d", &[2; 32], "L", "C"),
            mac("pw", "d", &[1; 32], "S", "C"),
            mac("pw", "d", &[1; 32], "L", "D"),
            // Lengths are part of it: moving a byte between parts is another message.
            mac("pw", "dL", &[1; 32], "", "C"),
        ] {
            assert_ne!(base, other);
        }
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
