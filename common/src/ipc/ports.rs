//! A role's ports: [`Outbox`] (a publisher and the notifier that wakes its subscribers)
//! and [`Inbox`] (a subscriber and the listener that wakes it).

use std::cell::Cell;
use std::fmt::Debug;
use std::mem::MaybeUninit;
use std::time::Duration;

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use iceoryx2::sample_mut::SampleMut;
use iceoryx2::sample_mut_uninit::SampleMutUninit;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;

use super::wait::{WAIT_BOUND_NS, Wait, wait_any_readable};
use super::{IpcError, iox};
use crate::clock::now_ns;
use crate::signals::shutdown_requested;
use crate::wire::SendCost;

/// A listener and a notifier on one event service.
pub type EventPorts = (Listener<ipc::Service>, Notifier<ipc::Service>);

/// A role's iceoryx2 node: it must outlive the role's ports.
pub type RoleNode = Node<ipc::Service>;

/// A publisher and the notifier that wakes its subscribers.
#[derive(Debug)]
pub struct Outbox<T: ZeroCopySend + Debug + Copy + 'static> {
    pub(super) service: PubSubFactory<ipc::Service, T, ()>,
    pub(super) publisher: Publisher<ipc::Service, T, ()>,
    pub(super) notifier: Notifier<ipc::Service>,
    /// A sample loaned (and maybe written) ahead of its send ([`Outbox::preloan`],
    /// [`Outbox::prewrite`]) and what the loan cost.
    pub(super) preloaned: Preloaned<T>,
}

/// A loaned sample not written yet: 200 bytes (its flat-buffer builder).
type Uninit<T> = SampleMutUninit<ipc::Service, MaybeUninit<T>, ()>;

/// A loaned sample written: 48 bytes, moved inline (no call to `memcpy`).
type Written<T> = SampleMut<ipc::Service, T, ()>;

/// The sample an [`Outbox`] loaned and wrote ahead of its next send, if any, and what its
/// loan cost (ns). It is held written ([`Outbox::preloan`] writes a default value, which
/// the send overwrites): taking an unwritten one out of the cell copied its 200 bytes with
/// a call to `memcpy` before the publish stamp (18 ns of the controller's preparation at
/// p50, by `rdtscp` marks).
pub(super) struct Preloaned<T: ZeroCopySend + Debug + Copy + 'static>(
    pub(super) Cell<Option<Held<T>>>,
);

/// A sample an [`Outbox`] holds for its next send.
pub(super) struct Held<T: ZeroCopySend + Debug + Copy + 'static> {
    sample: Written<T>,
    /// What its loan cost (ns).
    loan_ns: u64,
    /// Written with the value to send ([`Outbox::prewrite`]), not a placeholder
    /// ([`Outbox::preloan`]).
    prewritten: bool,
}

impl<T: ZeroCopySend + Debug + Copy + 'static> Preloaned<T> {
    /// `f` on the sample held, in place: not taken out and put back.
    #[inline]
    fn with<R>(&self, f: impl FnOnce(&mut Option<Held<T>>) -> R) -> R {
        // SAFETY: the cell is this outbox's alone and not `Sync`; no reference into it
        // outlives a call of `with`, and `f` (this module's closures) does not reach the
        // cell again, so this is its only reference while `f` runs.
        f(unsafe { &mut *self.0.as_ptr() })
    }

    /// The sample held, taken out (the cell is left empty).
    #[inline(always)]
    fn take(&self) -> Option<Held<T>> {
        self.0.take()
    }
}

impl<T: ZeroCopySend + Debug + Copy + 'static> Debug for Preloaned<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let what = self.with(|held| match held {
            None => "none",
            Some(h) if h.prewritten => "a written sample",
            Some(_) => "a sample",
        });
        write!(f, "Preloaned({what})")
    }
}

impl<T: ZeroCopySend + Debug + Copy + 'static> Outbox<T> {
    /// Loans the sample the next send writes, now, off the path that send is on (the
    /// controller after it published), and writes `T::default()` into it (the send
    /// overwrites it whole): the send then costs no loan, its [`SendCost::loan_ns`] is
    /// what this loan cost, and it takes a written sample's 48-byte handle out of the
    /// outbox, where an unwritten one's is 200 bytes. Keeps a sample already held.
    pub fn preloan(&self) -> Result<(), IpcError>
    where
        T: Default,
    {
        if self.preloaned.with(|held| held.is_some()) {
            return Ok(());
        }
        let (sample, loan_ns) = self.loan()?;
        let sample = sample.write_payload(T::default());
        self.preloaned.0.set(Some(Held { sample, loan_ns, prewritten: false }));
        Ok(())
    }

    /// Asks for the lines of the sample held ([`Outbox::preloan`], [`Outbox::prewrite`]),
    /// for writing ([`crate::prefetch::lines_for_write`]): its chunk of shared memory
    /// was last read by a subscriber on another core, and the send writes it. Nothing
    /// when none is held.
    #[inline]
    pub fn prefetch_loaned(&self) {
        self.preloaned.with(|held| {
            if let Some(h) = held {
                crate::prefetch::lines_for_write(h.sample.payload());
            }
        });
    }

    /// Loans a sample now, and what that cost (ns).
    #[inline]
    fn loan(&self) -> Result<(Uninit<T>, u64), IpcError> {
        let t0 = now_ns();
        let sample = self.publisher.loan_uninit().map_err(|e| iox("cannot loan a sample")(&e))?;
        Ok((sample, now_ns() - t0))
    }

    /// Loans a sample and writes `value` into it now, ahead of its send (the plant before
    /// it sleeps to its tick): [`Outbox::send_prewritten`] then writes only what its patch
    /// changes (the stamps), and the copy is not between the wake-up and the send. A
    /// sample already held is written again.
    pub fn prewrite(&self, value: T) -> Result<(), IpcError> {
        let (sample, loan_ns) = match self.preloaned.take() {
            Some(Held { mut sample, loan_ns, .. }) => {
                *sample.payload_mut() = value;
                (sample, loan_ns)
            }
            None => {
                let (s, ns) = self.loan()?;
                (s.write_payload(value), ns)
            }
        };
        self.preloaned.0.set(Some(Held { sample, loan_ns, prewritten: true }));
        Ok(())
    }

    /// The sample [`Outbox::prewrite`] wrote, in shared memory, for its owner to write in
    /// place before [`Outbox::send_prewritten`] (the C API's loan): `None` when none is
    /// held. The pointer stays valid until that send (the sample's memory does not move
    /// with the handle that owns it).
    pub fn prewritten_ptr(&self) -> Option<*mut T> {
        self.preloaned.with(|held| match held {
            Some(h) if h.prewritten => Some(std::ptr::from_mut(h.sample.payload_mut())),
            _ => None,
        })
    }

    /// Sends the sample [`Outbox::prewrite`] wrote, `patch`ed with the publish stamp it is
    /// given, and notifies; `after` gets `value` (what was prewritten) patched the same way,
    /// as published. A sample held but not written ahead ([`Outbox::preloan`]) is written
    /// with `value` first; with none held, a plain [`Outbox::send_then`] of `value`
    /// patched.
    #[inline]
    pub fn send_prewritten(
        &self,
        mut value: T,
        patch: impl Fn(&mut T, u64),
        after: impl FnOnce(&T),
    ) -> Result<SendCost, IpcError> {
        let Some(Held { mut sample, loan_ns, prewritten }) = self.preloaned.take() else {
            return self.send_then(value, |v| patch(v, now_ns()), after);
        };
        if !prewritten {
            *sample.payload_mut() = value;
        }
        let t1 = now_ns();
        patch(sample.payload_mut(), t1);
        let cost = self.send_and_notify(sample, loan_ns, t1)?;
        patch(&mut value, t1);
        after(&value);
        Ok(cost)
    }

    /// Waits until at least `n` subscribers are connected (those that must see the first
    /// sample), polling every millisecond; false on a termination signal.
    pub fn wait_for_subscribers(&self, n: usize) -> bool {
        while self.subscribers() < n {
            if shutdown_requested() {
                return false;
            }
            self.update_connections();
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        self.update_connections();
        true
    }

    /// Publishes `value` (written in place into shared memory) and notifies listeners.
    /// `stamp` is called just before the send to set the publish timestamp. Returns what
    /// each step cost (for the stage breakdown; four clock reads).
    #[inline]
    pub fn send(&self, value: T, stamp: impl FnOnce(&mut T)) -> Result<SendCost, IpcError> {
        self.send_then(value, stamp, |_| ())
    }

    /// [`Outbox::send`], then `after` with the sample as published (its flight record),
    /// once the listeners are notified: off the hop it starts.
    #[inline]
    pub fn send_then(
        &self,
        value: T,
        stamp: impl FnOnce(&mut T),
        after: impl FnOnce(&T),
    ) -> Result<SendCost, IpcError> {
        self.send_stamped(value, |v, _| stamp(v), after)
    }

    /// [`Outbox::send_then`] with `stamp` given the clock read that starts the send (the
    /// publish stamp, as [`Outbox::send_prewritten`] gives it): one clock read fewer
    /// than a stamp that reads the clock again.
    #[inline]
    pub fn send_stamped(
        &self,
        mut value: T,
        stamp: impl FnOnce(&mut T, u64),
        after: impl FnOnce(&T),
    ) -> Result<SendCost, IpcError> {
        let (sample, loan_ns, t1) = self.write_sample(|t1| {
            stamp(&mut value, t1);
            value
        })?;
        let cost = self.send_and_notify(sample, loan_ns, t1)?;
        after(&value);
        Ok(cost)
    }

    /// [`Outbox::send_stamped`] of a value taken by reference: after the clock read that
    /// starts the send (the publish stamp), it is written into the sample and `patch`ed
    /// there with that stamp; `after` gets a copy patched the same way, once the
    /// listeners are notified. Nothing of the value is copied before the stamp, and
    /// nothing but the copy into the sample before the send, so the value need not be
    /// built for the send (the controller's answer, kept for its resume slot).
    #[inline]
    pub fn send_patched(
        &self,
        value: &T,
        patch: impl Fn(&mut T, u64),
        after: impl FnOnce(&T),
    ) -> Result<SendCost, IpcError> {
        let (mut sample, loan_ns, t1) = self.write_sample(|_| *value)?;
        patch(sample.payload_mut(), t1);
        let cost = self.send_and_notify(sample, loan_ns, t1)?;
        let mut sent = *value;
        patch(&mut sent, t1);
        after(&sent);
        Ok(cost)
    }

    /// The sample a send goes out in (the one held, else one loaned now), written with
    /// `value(t1)`, and what its loan cost; `t1`, the publish stamp, is read once the
    /// sample is in hand, before it is written.
    #[inline(always)]
    fn write_sample(
        &self,
        value: impl FnOnce(u64) -> T,
    ) -> Result<(Written<T>, u64, u64), IpcError> {
        Ok(match self.preloaned.take() {
            Some(Held { mut sample, loan_ns, .. }) => {
                let t1 = now_ns();
                *sample.payload_mut() = value(t1);
                (sample, loan_ns, t1)
            }
            None => {
                let (s, loan_ns) = self.loan()?;
                let t1 = now_ns();
                (s.write_payload(value(t1)), loan_ns, t1)
            }
        })
    }

    /// Sends a written sample and notifies the listeners: what the loan cost (`loan_ns`),
    /// the send from `t1` (the publish stamp) and the notify.
    #[inline]
    fn send_and_notify(
        &self,
        sample: SampleMut<ipc::Service, T, ()>,
        loan_ns: u64,
        t1: u64,
    ) -> Result<SendCost, IpcError> {
        sample.send().map_err(|e| iox("cannot send a sample")(&e))?;
        let t2 = now_ns();
        self.notifier.notify().map_err(|e| iox("cannot notify")(&e))?;
        Ok(SendCost { loan_ns, send_ns: t2 - t1, notify_ns: now_ns() - t2 })
    }

    /// Loans a sample and never sends it, until a termination signal: a test hook for
    /// "killed while holding a loan" (iceoryx2 must reclaim the loan after the kill).
    pub fn stall_holding_a_loan(&self) -> Result<(), IpcError> {
        let sample = self.publisher.loan_uninit().map_err(|e| iox("cannot loan a sample")(&e))?;
        while !shutdown_requested() {
            std::thread::sleep(Duration::from_millis(5));
        }
        drop(sample);
        Ok(())
    }

    /// Connects subscribers that appeared since the last send (and gives them history).
    pub fn update_connections(&self) {
        let _ = self.publisher.update_connections();
    }

    /// Subscribers currently connected to this topic.
    pub fn subscribers(&self) -> usize {
        self.service.dynamic_config().number_of_subscribers()
    }

    /// Subscribers of this topic that belong to none of `nodes` (a link gateway's).
    pub fn subscribers_except(&self, nodes: &[u128]) -> usize {
        let mut n = 0;
        self.service.dynamic_config().list_subscribers(|d| {
            n += usize::from(!nodes.contains(&d.node_id.value()));
            CallbackProgression::Continue
        });
        n
    }
}

/// A subscriber and, optionally, the listener that wakes it.
#[derive(Debug)]
pub struct Inbox<T: ZeroCopySend + Debug + Copy + 'static> {
    pub(super) subscriber: Subscriber<ipc::Service, T, ()>,
    pub(super) listener: Option<Listener<ipc::Service>>,
    /// See [`Inbox::unnotified`].
    pub(super) unnotified: Cell<u64>,
}

impl<T: ZeroCopySend + Debug + Copy + 'static> Inbox<T> {
    /// Takes every waiting sample, oldest first, handing each to `f`.
    #[inline]
    pub fn drain(&self, mut f: impl FnMut(T)) -> Result<(), IpcError> {
        while let Some(x) = self.take()? {
            f(x);
        }
        Ok(())
    }

    /// Takes the oldest waiting sample, if any.
    #[inline]
    pub fn take(&self) -> Result<Option<T>, IpcError> {
        match self.subscriber.receive() {
            Ok(Some(s)) => Ok(Some(*s.payload())),
            Ok(None) => Ok(None),
            Err(e) => Err(iox("cannot receive")(&e)),
        }
    }

    /// Lost wake-ups: how often [`Inbox::wait_for`] found what it waited for only after a
    /// whole bounded wait (10 ms) passed with no notification. Every publisher notifies
    /// after it sends, so on one host this stays 0; a sample that comes in through a link
    /// gateway without a wake-up after it counts here (and costs its receiver up to 10 ms).
    /// (A sample that lands in the microsecond between the bound's end and the look after
    /// it counts too, falsely; that needs a 10 ms silence first.)
    pub fn unnotified(&self) -> u64 {
        self.unnotified.get()
    }

    /// Waits until `ready()` returns something, the monotonic deadline passes, or a
    /// termination signal arrives. `ready` is polled first, after every wake-up, and in
    /// spin mode continuously; it should drain the inbox.
    #[inline]
    pub fn wait_for<R>(
        &self,
        wait: Wait,
        deadline_ns: u64,
        mut ready: impl FnMut(&Self) -> Result<Option<R>, IpcError>,
    ) -> Result<Option<R>, IpcError> {
        let start = now_ns();
        let mut slept_through = false;
        loop {
            if let Some(r) = ready(self)? {
                if slept_through {
                    self.unnotified.set(self.unnotified.get() + 1);
                }
                return Ok(Some(r));
            }
            let now = now_ns();
            if now >= deadline_ns || shutdown_requested() {
                return Ok(None);
            }
            let spin = match wait {
                Wait::Spin => true,
                Wait::Event => false,
                Wait::Hybrid { spin_ns } => now - start < spin_ns,
                Wait::Poll { period_ns } => {
                    let nap = period_ns.min(deadline_ns - now).min(10_000_000);
                    std::thread::sleep(Duration::from_nanos(nap));
                    continue;
                }
            };
            let left = deadline_ns - now;
            slept_through = match (&self.listener, spin || left < 2_000) {
                // Bounded so that signals are seen; wake-ups merge, so drain after. A
                // silent wait counts only when the bound, not the deadline, ended it.
                (Some(l), false) => {
                    !wait_readable(l, left.min(WAIT_BOUND_NS))? && left > WAIT_BOUND_NS
                }
                _ => {
                    std::hint::spin_loop();
                    false
                }
            };
        }
    }
}

/// Blocks until `listener` has an event or `timeout_ns` passes, then drains its events.
///
/// Not iceoryx2's `Listener::timed_wait`: it sets the timeout as `SO_RCVTIMEO`, which Linux
/// counts in jiffies (4 ms at `HZ=250`), so a 1 ms timeout blocked 4–8 ms here (found as
/// real-time ticks late by up to 8 ms whenever a torque did not come; and a timeout under
/// 1 µs becomes `{0, 0}`: wait forever). `ppoll` on the listener's socket has an hrtimer
/// timeout with nanosecond resolution; the listener is drained with `try_wait` after.
/// Returns whether a notification (or a signal) came.
fn wait_readable(listener: &Listener<ipc::Service>, timeout_ns: u64) -> Result<bool, IpcError> {
    use iceoryx2_bb_posix::file_descriptor::FileDescriptorBased;
    // SAFETY: the listener owns the descriptor and outlives this call; it is only polled.
    let fd = unsafe { listener.file_descriptor().native_handle() };
    wait_any_readable(&[fd], timeout_ns)?;
    let mut notified = false;
    match listener.try_wait(|_| notified = true) {
        Ok(_) => Ok(notified),
        // A signal (SIGTERM to stop, say) is a wake-up like any other.
        Err(iceoryx2::port::listener::ListenerWaitError::InterruptSignal) => Ok(true),
        Err(e) => Err(iox("cannot drain events")(&e)),
    }
}
