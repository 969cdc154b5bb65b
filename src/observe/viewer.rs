//! A minimal viewer of the Foxglove WebSocket protocol, written against the protocol, not
//! with the SDK: it offers one subprotocol (`foxglove.sdk.v1` unless told), reads the
//! server's `advertise` (topics, encodings, schemas), subscribes to topics by name, decodes
//! message data frames (opcode 1: subscription id, log time, payload) and closes as RFC 6455
//! says. The tests use it to check `rotorloop foxglove` as
//! a viewer would; `bench --before-after foxglove` uses it to load the server as a viewer
//! subscribed to every topic does.

use std::collections::HashMap;
use std::net::TcpStream;
use std::time::Duration;

use anyhow::{Context as _, bail};
use serde_json::Value;
use tungstenite::client::IntoClientRequest;
use tungstenite::{Message, WebSocket};

/// The subprotocol this viewer offers.
pub const SUBPROTOCOL: &str = "foxglove.sdk.v1";

/// A message on a subscribed topic.
#[derive(Debug, Clone)]
pub struct Received {
    /// Its topic.
    pub topic: String,
    /// Its log time (ns).
    pub log_time: u64,
    /// Its payload (JSON text or protobuf, as the channel's encoding says).
    pub payload: Vec<u8>,
}

/// A connection to a Foxglove WebSocket server.
#[derive(Debug)]
pub struct Viewer {
    ws: WebSocket<TcpStream>,
    /// The subprotocol the server accepted.
    pub subprotocol: String,
    /// Advertised channels: id → (topic, encoding).
    pub channels: HashMap<u64, (String, String)>,
    /// The advertised schemas: topic → (schema name, schema text as advertised).
    pub schemas: HashMap<String, (String, String)>,
    subscriptions: HashMap<u32, String>,
    wanted: Vec<String>,
    next_id: u32,
}

impl Viewer {
    /// Connects to `addr` (`HOST:PORT`), offering [`SUBPROTOCOL`]; reads time out after
    /// `poll` so [`Viewer::receive`] returns `None` while nothing comes.
    pub fn connect(addr: &str, poll: Duration) -> anyhow::Result<Self> {
        Self::connect_with(addr, poll, SUBPROTOCOL)
    }

    /// Connects to `addr` offering `subprotocol` only.
    pub fn connect_with(addr: &str, poll: Duration, subprotocol: &str) -> anyhow::Result<Self> {
        let offered = subprotocol;
        let stream =
            TcpStream::connect(addr).with_context(|| format!("cannot connect to {addr}"))?;
        stream.set_read_timeout(Some(poll))?;
        stream.set_nodelay(true)?;
        let mut req = format!("ws://{addr}/").into_client_request()?;
        req.headers_mut().insert("Sec-WebSocket-Protocol", offered.parse()?);
        let (ws, response) =
            tungstenite::client(req, stream).map_err(|e| anyhow::anyhow!("handshake: {e}"))?;
        let subprotocol = response
            .headers()
            .get("sec-websocket-protocol")
            .and_then(|v| v.to_str().ok())
            .unwrap_or_default()
            .to_owned();
        if subprotocol != offered {
            bail!("the server speaks `{subprotocol}`, not {offered}");
        }
        Ok(Self {
            ws,
            subprotocol,
            channels: HashMap::new(),
            schemas: HashMap::new(),
            subscriptions: HashMap::new(),
            wanted: Vec::new(),
            next_id: 1,
        })
    }

    /// Subscribes to `topics`: those advertised already now, the others when they are.
    pub fn subscribe(&mut self, topics: &[&str]) -> anyhow::Result<()> {
        self.wanted.extend(topics.iter().map(|t| (*t).to_owned()));
        let ids: Vec<u64> = self.channels.keys().copied().collect();
        self.subscribe_wanted(&ids)
    }

    fn subscribe_wanted(&mut self, channel_ids: &[u64]) -> anyhow::Result<()> {
        let mut subs = Vec::new();
        for id in channel_ids {
            let Some((topic, _)) = self.channels.get(id) else { continue };
            let taken = self.subscriptions.values().any(|t| t == topic);
            if taken || !self.wanted.iter().any(|w| w == "*" || w == topic) {
                continue;
            }
            let sub = self.next_id;
            self.next_id += 1;
            self.subscriptions.insert(sub, topic.clone());
            subs.push(serde_json::json!({"id": sub, "channelId": id}));
        }
        if !subs.is_empty() {
            let m = serde_json::json!({"op": "subscribe", "subscriptions": subs});
            self.ws.send(Message::text(m.to_string()))?;
        }
        Ok(())
    }

    /// The next message on a subscribed topic, or `None` when nothing came within the
    /// poll time. Control messages (advertise, server info, status) are handled on the way.
    pub fn receive(&mut self) -> anyhow::Result<Option<Received>> {
        loop {
            let m = match self.ws.read() {
                Ok(m) => m,
                Err(tungstenite::Error::Io(e))
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    return Ok(None);
                }
                Err(e) => return Err(e.into()),
            };
            match m {
                Message::Text(t) => self.control(&t)?,
                Message::Binary(b) => {
                    if let Some(r) = self.data(&b) {
                        return Ok(Some(r));
                    }
                }
                Message::Close(f) => match f {
                    Some(f) => bail!(
                        "the server closed the connection ({}: {})",
                        u16::from(f.code),
                        f.reason
                    ),
                    None => bail!("the server closed the connection (no code)"),
                },
                _ => {}
            }
        }
    }

    fn control(&mut self, text: &str) -> anyhow::Result<()> {
        let v: Value = serde_json::from_str(text).context("a control message that is not JSON")?;
        match v["op"].as_str() {
            Some("advertise") => {
                let mut ids = Vec::new();
                for c in v["channels"].as_array().into_iter().flatten() {
                    let (Some(id), Some(topic)) = (c["id"].as_u64(), c["topic"].as_str()) else {
                        continue;
                    };
                    let encoding = c["encoding"].as_str().unwrap_or_default().to_owned();
                    self.channels.insert(id, (topic.to_owned(), encoding));
                    let text = |k: &str| c[k].as_str().unwrap_or_default().to_owned();
                    self.schemas.insert(topic.to_owned(), (text("schemaName"), text("schema")));
                    ids.push(id);
                }
                self.subscribe_wanted(&ids)?;
            }
            Some("unadvertise") => {
                for id in v["channelIds"].as_array().into_iter().flatten().filter_map(Value::as_u64)
                {
                    if let Some((topic, _)) = self.channels.remove(&id) {
                        self.subscriptions.retain(|_, t| *t != topic);
                    }
                }
            }
            _ => {}
        }
        Ok(())
    }

    /// A message data frame: opcode 1, subscription id (u32 LE), log time (u64 LE), payload.
    fn data(&self, b: &[u8]) -> Option<Received> {
        if b.len() < 13 || b[0] != 1 {
            return None;
        }
        let sub = u32::from_le_bytes(b[1..5].try_into().ok()?);
        let log_time = u64::from_le_bytes(b[5..13].try_into().ok()?);
        let topic = self.subscriptions.get(&sub)?.clone();
        Some(Received { topic, log_time, payload: b[13..].to_vec() })
    }

    /// Drops the connection without a close handshake: a viewer that vanished.
    pub fn vanish(self) {
        let _ = self.ws.get_ref().shutdown(std::net::Shutdown::Both);
    }

    /// Closes as RFC 6455 says (a close frame, code 1000) and reads until the server's
    /// close or `patience`: the server's close code (`None`: no close came), the data frames
    /// that came after ours, and whether anything came after the server's close.
    pub fn close(mut self, patience: Duration) -> anyhow::Result<Closed> {
        use tungstenite::protocol::{CloseFrame, frame::coding::CloseCode};
        self.ws.close(Some(CloseFrame { code: CloseCode::Normal, reason: "".into() }))?;
        self.read_close(patience)
    }

    /// Writes `bytes` as they are (a frame made by hand), then reads until the server's
    /// close or `patience`, as [`Viewer::close`].
    pub fn send_raw(mut self, bytes: &[u8], patience: Duration) -> anyhow::Result<Closed> {
        use std::io::Write as _;
        self.ws.get_mut().write_all(bytes)?;
        self.read_close(patience)
    }

    fn read_close(&mut self, patience: Duration) -> anyhow::Result<Closed> {
        let until = std::time::Instant::now() + patience;
        let mut closed = Closed::default();
        while std::time::Instant::now() < until {
            match self.ws.read() {
                Ok(Message::Close(frame)) if closed.code.is_none() => {
                    closed.code = Some(frame.map_or(1005, |f| u16::from(f.code)));
                }
                Ok(_) if closed.code.is_some() => closed.after_close += 1,
                Ok(Message::Binary(_) | Message::Text(_)) => closed.data_after_ours += 1,
                Ok(_) => {}
                Err(tungstenite::Error::Io(e))
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(tungstenite::Error::ConnectionClosed | tungstenite::Error::AlreadyClosed) => {
                    closed.ended = true;
                    break;
                }
                Err(_) => break,
            }
        }
        Ok(closed)
    }
}

/// What came back after a viewer closed, or sent a bad frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Closed {
    /// The server's close code (1005: a close without one); `None`: no close came.
    pub code: Option<u16>,
    /// Data frames between the viewer's close and the server's.
    pub data_after_ours: u64,
    /// Frames after the server's close (none are allowed).
    pub after_close: u64,
    /// The server ended the connection after its close.
    pub ended: bool,
}
