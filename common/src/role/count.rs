//! Counting what a subscriber received, lost and saw again ([`SeqCounter`]).

/// Counts samples received and samples lost (gaps in the tick sequence) on one subscriber.
/// Every topic of a run starts at tick 0: a fresh counter counts the ticks before its first
/// sample as lost (a starved subscriber whose small buffer overflowed before it first
/// looked loses the oldest, and they are losses like any gap). A restart that does not
/// know its predecessor's last tick ([`SeqCounter::resume_unanchored`]) cannot, and does
/// not count the gap before its first sample.
#[derive(Debug, Clone, Copy, Default)]
pub struct SeqCounter {
    /// Samples of new ticks taken.
    pub received: u64,
    /// Ticks skipped between consecutive samples.
    pub lost: u64,
    /// Samples of a tick already seen (a restarted publisher repeating its last one).
    pub repeated: u64,
    last: Option<u64>,
    /// Resumed without the predecessor's last tick: the first gap is unknown.
    unanchored: bool,
}

impl SeqCounter {
    /// Accounts for a sample of tick `tick`. Repeated or older ticks (a restarted
    /// publisher re-sending its last sample) count as repeated, not received.
    #[inline]
    pub fn see(&mut self, tick: u64) {
        match self.last {
            Some(last) if tick <= last => self.repeated += 1,
            Some(last) => {
                self.received += 1;
                self.lost += tick - last - 1;
                self.last = Some(tick);
            }
            None => {
                self.received += 1;
                if !self.unanchored {
                    self.lost += tick;
                }
                self.last = Some(tick);
            }
        }
    }

    /// Continue counting from these totals without the predecessor's last tick (its
    /// resume slot names none): the gap before the first sample is not counted.
    pub fn resume_unanchored(received: u64, lost: u64) -> Self {
        Self { received, lost, repeated: 0, last: None, unanchored: true }
    }

    /// Continue counting after `last` (a restarted subscriber).
    pub fn resume(received: u64, lost: u64, last: u64) -> Self {
        Self { received, lost, repeated: 0, last: Some(last), unanchored: false }
    }

    /// The newest tick seen.
    pub fn last(&self) -> Option<u64> {
        self.last
    }
}

#[cfg(test)]
mod tests {
    use super::SeqCounter;

    #[test]
    fn every_tick_is_received_lost_or_repeated_from_tick_zero() {
        // A starved subscriber whose buffer overflowed before it first looked: 0-3 lost.
        let mut c = SeqCounter::default();
        for k in [4, 5, 5, 8, 7, 9] {
            c.see(k);
        }
        assert_eq!((c.received, c.lost, c.repeated), (4, 6, 2), "0-3 and 6-7 lost");
        assert_eq!(c.received + c.lost, 9 + 1);
        // A restart that does not know its predecessor's last tick cannot count the first
        // gap; an anchored one continues after that tick.
        let mut u = SeqCounter::resume_unanchored(4, 0);
        u.see(10);
        assert_eq!((u.received, u.lost), (5, 0));
        let mut a = SeqCounter::resume(10, 2, 11);
        a.see(13);
        assert_eq!((a.received, a.lost, a.last()), (11, 3, Some(13)));
    }
}
