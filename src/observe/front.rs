//! The live view's WebSocket front: what a viewer connects to. The Foxglove SDK's server
//! (`foxglove` 0.30) speaks the Foxglove protocol behind it, on a loopback port of its own;
//! the front relays each viewer's messages to it and its messages back, and keeps the
//! WebSocket's own rules (RFC 6455) that the SDK's server does not:
//!
//! - **A close is answered.** The SDK's server stops reading a connection at the viewer's
//!   close frame and never sends the reply its WebSocket layer queued (tungstenite sends it
//!   on the next read or write, and none comes): a viewer that closes waits out its own
//!   timeout. Here the viewer's close is answered at once with its own code, nothing else
//!   is sent after it, and the TCP connection is closed.
//! - **A bad frame gets its close code**: text that is not UTF-8 `1007`, a frame or message
//!   over [`MAX_MESSAGE`] bytes `1009`, a protocol violation `1002` (the SDK's server
//!   dropped the connection without one). A viewer only ever sends small JSON requests.
//! - **The loop's end is said**: `1001` (going away) when the server stops.
//! - **Both names of the protocol**: `foxglove.sdk.v1.1`, `foxglove.sdk.v1` and the older
//!   `foxglove.websocket.v1` (the same protocol as `foxglove.sdk.v1`, which the SDK's server
//!   refuses with `400`): the newest one offered is answered, and the SDK is spoken to in
//!   `foxglove.sdk.v1` (`foxglove.sdk.v1.1` where that was chosen).
//!
//! A viewer that does not keep up is held up here (its writes wait) and so stops reading
//! from the SDK, which drops the oldest messages for it as before.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_tungstenite::tungstenite::handshake::server::{Request, Response};
use tokio_tungstenite::tungstenite::http::HeaderValue;
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::protocol::{CloseFrame, WebSocketConfig};
use tokio_tungstenite::tungstenite::{Error, Message, client::IntoClientRequest};
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

/// The subprotocols a viewer may offer, the preferred first.
pub const SUBPROTOCOLS: [&str; 3] =
    ["foxglove.sdk.v1.1", "foxglove.sdk.v1", "foxglove.websocket.v1"];

/// The largest frame or message a viewer may send (bytes): larger is closed with `1009`.
pub const MAX_MESSAGE: usize = 1 << 20;

/// How long a viewer has to complete its handshake, and to answer our close.
const PATIENCE: Duration = Duration::from_secs(5);

/// The front, serving until dropped.
#[derive(Debug)]
pub struct Front {
    runtime: tokio::runtime::Runtime,
    /// The viewers' connections not yet ended.
    open: Arc<AtomicUsize>,
}

/// Counts a viewer's connection while it lasts.
struct Open(Arc<AtomicUsize>);

impl Open {
    fn new(count: &Arc<AtomicUsize>) -> Self {
        count.fetch_add(1, Ordering::SeqCst);
        Self(Arc::clone(count))
    }
}

impl Drop for Open {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

impl Front {
    /// Serves viewers on `listener`, relaying each to the SDK's server at `upstream`.
    pub fn start(listener: std::net::TcpListener, upstream: SocketAddr) -> std::io::Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("foxglove-front")
            .enable_all()
            .build()?;
        listener.set_nonblocking(true)?;
        let listener = {
            let _in = runtime.enter();
            TcpListener::from_std(listener)?
        };
        let open = Arc::new(AtomicUsize::new(0));
        let count = Arc::clone(&open);
        runtime.spawn(async move {
            while let Ok((stream, _)) = listener.accept().await {
                let _ = stream.set_nodelay(true);
                let open = Open::new(&count);
                tokio::spawn(async move {
                    viewer(stream, upstream).await;
                    drop(open);
                });
            }
        });
        Ok(Self { runtime, open })
    }

    /// Called once the SDK's server has stopped: gives the viewers up to `wait` to be told
    /// (`1001`, each relay's close) and their connections to end, then stops. The runtime's
    /// shutdown drops a task where it stands: stopping at once once cut a viewer off in
    /// the middle of its close (a reset, no close frame).
    pub fn stop(self, wait: Duration) {
        let until = std::time::Instant::now() + wait;
        while self.open.load(Ordering::SeqCst) > 0 && std::time::Instant::now() < until {
            std::thread::sleep(Duration::from_millis(5));
        }
        self.runtime.shutdown_timeout(Duration::ZERO);
    }
}

/// The subprotocol answered to a viewer offering `offered`, and the one spoken to the SDK.
pub fn choose(offered: &[&str]) -> Option<(&'static str, &'static str)> {
    let best = SUBPROTOCOLS.iter().find(|p| offered.iter().any(|o| o.trim() == **p))?;
    let upstream = if *best == SUBPROTOCOLS[0] { SUBPROTOCOLS[0] } else { SUBPROTOCOLS[1] };
    Some((best, upstream))
}

fn config() -> WebSocketConfig {
    WebSocketConfig::default().max_message_size(Some(MAX_MESSAGE)).max_frame_size(Some(MAX_MESSAGE))
}

/// One viewer: the handshake, the SDK's connection, the relay until either closes.
async fn viewer(stream: TcpStream, upstream: SocketAddr) {
    let mut chosen = None;
    // The callback's type is tungstenite's (its error is the HTTP response refusing).
    #[allow(clippy::result_large_err)]
    let callback = |req: &Request, mut res: Response| {
        let offered: Vec<&str> = req
            .headers()
            .get_all("sec-websocket-protocol")
            .iter()
            .flat_map(|h| h.to_str().unwrap_or_default().split(','))
            .collect();
        match choose(&offered) {
            Some((ours, sdk)) => {
                res.headers_mut().insert("sec-websocket-protocol", HeaderValue::from_static(ours));
                chosen = Some(sdk);
                Ok(res)
            }
            None => Err(Response::builder()
                .status(400)
                .body(Some(format!("offer one of the subprotocols {}", SUBPROTOCOLS.join(", "))))
                .unwrap_or_default()),
        }
    };
    let accepted =
        tokio_tungstenite::accept_hdr_async_with_config(stream, callback, Some(config()));
    let Ok(Ok(mut client)) = tokio::time::timeout(PATIENCE, accepted).await else { return };
    let Some(sdk) = chosen else { return };
    let sdk = match connect(upstream, sdk).await {
        Ok(s) => s,
        Err(_) => {
            let why = "the live view's server is not there";
            close(&mut client, CloseCode::Error, why).await;
            return;
        }
    };
    relay(client, sdk).await;
}

type Sdk = WebSocketStream<MaybeTlsStream<TcpStream>>;

async fn connect(upstream: SocketAddr, subprotocol: &'static str) -> Result<Sdk, Error> {
    let mut req = format!("ws://{upstream}/").into_client_request()?;
    req.headers_mut().insert("sec-websocket-protocol", HeaderValue::from_static(subprotocol));
    Ok(tokio_tungstenite::connect_async(req).await?.0)
}

/// Relays until the viewer or the SDK's server closes, or the connection fails.
async fn relay(mut client: WebSocketStream<TcpStream>, mut sdk: Sdk) {
    loop {
        tokio::select! {
            m = client.next() => match m {
                // Answered with its own code (tungstenite queued the reply; closing the
                // sink sends it: `WebSocketStream::close` would send a close of its own,
                // refused after the viewer's), and nothing after it.
                Some(Ok(Message::Close(_))) => {
                    let _ = SinkExt::close(&mut client).await;
                    break;
                }
                Some(Ok(m @ (Message::Text(_) | Message::Binary(_)))) => {
                    if sdk.send(m).await.is_err() {
                        close(&mut client, CloseCode::Error, "the live view's server failed").await;
                        break;
                    }
                }
                // Pings are answered by the WebSocket layer itself.
                Some(Ok(_)) => {}
                Some(Err(e)) => {
                    if let Some((code, why)) = close_code(&e) {
                        close(&mut client, code, why).await;
                    }
                    break;
                }
                None => break,
            },
            m = sdk.next() => match m {
                Some(Ok(m @ (Message::Text(_) | Message::Binary(_)))) => {
                    if client.send(m).await.is_err() {
                        break;
                    }
                }
                Some(Ok(Message::Close(_)) | Err(_)) | None => {
                    close(&mut client, CloseCode::Away, "the live view has ended").await;
                    break;
                }
                Some(Ok(_)) => {}
            },
        }
    }
    let _ = tokio::time::timeout(PATIENCE, sdk.close(None)).await;
}

/// The close code of a viewer's frame that failed, if it is one of a bad frame.
fn close_code(e: &Error) -> Option<(CloseCode, &'static str)> {
    match e {
        Error::Utf8(_) => Some((CloseCode::Invalid, "text that is not UTF-8")),
        Error::Capacity(_) => Some((CloseCode::Size, "a frame or message over 1 MiB")),
        Error::Protocol(_) => Some((CloseCode::Protocol, "a protocol violation")),
        _ => None,
    }
}

/// Sends our close (`code`, `why`) and waits a while for the viewer's answer.
async fn close(client: &mut WebSocketStream<TcpStream>, code: CloseCode, why: &'static str) {
    let frame = CloseFrame { code, reason: why.into() };
    if client.send(Message::Close(Some(frame))).await.is_err() {
        return;
    }
    let answered = async {
        while let Some(Ok(m)) = client.next().await {
            if m.is_close() {
                break;
            }
        }
    };
    let _ = tokio::time::timeout(PATIENCE, answered).await;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The newest subprotocol offered is answered, the older name of the protocol too, and
    /// the SDK is spoken to in the one it knows.
    #[test]
    fn the_newest_offered_subprotocol_is_chosen() {
        assert_eq!(
            choose(&["foxglove.websocket.v1"]),
            Some(("foxglove.websocket.v1", "foxglove.sdk.v1"))
        );
        assert_eq!(
            choose(&[" foxglove.sdk.v1", "foxglove.websocket.v1"]),
            Some(("foxglove.sdk.v1", "foxglove.sdk.v1"))
        );
        assert_eq!(
            choose(&["foxglove.sdk.v1", "foxglove.sdk.v1.1"]),
            Some(("foxglove.sdk.v1.1", "foxglove.sdk.v1.1"))
        );
        assert_eq!(choose(&["foxglove.websocket"]), None);
    }
}
