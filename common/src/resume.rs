//! Resume slots: where a role keeps a copy of the last sample it published, so that a
//! restarted process (after `kill -9`) continues where its predecessor stopped.
//!
//! iceoryx2's history cannot serve here: it lives in the publisher's data segment, which
//! is removed when the dead node is cleaned up. A slot is a small file in `/dev/shm`
//! named `rl_<domain>_resume_<role>` (so domain clean-up and leftover checks cover it),
//! mapped into memory and written with two copies and a generation counter: a process
//! killed in the middle of a write leaves the previous copy valid. Writing is a `memcpy`
//! and an atomic store, no system call.

use std::cell::Cell;
use std::marker::PhantomData;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering, fence};

use iceoryx2::prelude::ZeroCopySend;

use crate::ipc::IpcError;
use crate::ipc::domain::Domain;
use crate::wire::{LAYOUT_VERSION, StateSample};

const MAGIC: u64 = 0x726c_7265_7375_6d65; // "rlresume"
const HEADER: usize = 64;

/// A mapped resume slot for samples of type `T`.
#[derive(Debug)]
pub struct ResumeSlot<T: Copy + ZeroCopySend> {
    map: *mut u8,
    len: usize,
    _t: PhantomData<T>,
    /// How many [`Stored`] borrows of the copy last stored are alive: a store meanwhile
    /// would write that copy under them (the one after next does), so it panics.
    lent: Cell<u32>,
    /// The generation this process published last (0: none), which [`ResumeSlot::stored`]
    /// reads: not the file's word, which another process could change meanwhile.
    mine: Cell<u64>,
}

/// The value a [`ResumeSlot`] stored last, borrowed in place ([`ResumeSlot::stored`]).
#[derive(Debug)]
pub struct Stored<'a, T: Copy + ZeroCopySend> {
    slot: &'a ResumeSlot<T>,
    value: &'a T,
}

impl<T: Copy + ZeroCopySend> std::ops::Deref for Stored<'_, T> {
    type Target = T;

    #[inline]
    fn deref(&self) -> &T {
        self.value
    }
}

impl<T: Copy + ZeroCopySend> Drop for Stored<'_, T> {
    #[inline]
    fn drop(&mut self) {
        self.slot.lent.set(self.slot.lent.get() - 1);
    }
}

impl<T: Copy + ZeroCopySend> ResumeSlot<T> {
    /// The slot file of `role` in `domain`.
    pub fn path(domain: &Domain, role: &str) -> PathBuf {
        PathBuf::from(format!("/dev/shm/{}resume_{role}", domain.prefix()))
    }

    /// Opens (or creates) the slot of `role` in `domain`.
    pub fn open(domain: &Domain, role: &str) -> Result<Self, IpcError> {
        Self::map(domain, role, true)?.ok_or_else(|| IpcError::Iceoryx {
            what: format!("resume slot {}", Self::path(domain, role).display()),
            detail: "could not be created".into(),
        })
    }

    /// Opens the slot of `role` in `domain` if it exists and was written by this layout;
    /// never creates or changes it (for observers: `rotorloop ps` and `watch`).
    pub fn open_existing(domain: &Domain, role: &str) -> Result<Option<Self>, IpcError> {
        Self::map(domain, role, false)
    }

    fn map(domain: &Domain, role: &str, create: bool) -> Result<Option<Self>, IpcError> {
        let path = Self::path(domain, role);
        let err = |what: &str, e: std::io::Error| IpcError::Iceoryx {
            what: format!("resume slot {}: {what}", path.display()),
            detail: e.to_string(),
        };
        let len = HEADER + 2 * size_of::<T>().next_multiple_of(64);
        // Made by this role, exclusively and owner-only, or this user's own: a slot
        // another user planted (or a link) is refused, never loaded (`crate::private`).
        let file = match create {
            true => crate::private::open_or_create_file(&path)?.0,
            false => match crate::private::open_file(&path) {
                Ok(Some(f)) => f,
                // An observer reads only what it may: nothing, or another user's, is none.
                Ok(None) | Err(_) => return Ok(None),
            },
        };
        if file.metadata().map_err(|e| err("stat", e))?.len() != len as u64 {
            if !create {
                return Ok(None); // another layout's slot
            }
            file.set_len(len as u64).map_err(|e| err("size", e))?;
        }
        // `len` bytes of a file of exactly that size.
        let map = crate::private::map_shared(&file, len, 0).map_err(|e| err("mmap", e))?;
        let slot = Self { map, len, _t: PhantomData, lent: Cell::new(0), mine: Cell::new(0) };
        let (magic, size, version) = (slot.word(0), slot.word(1), slot.word(2));
        if magic.load(Ordering::Acquire) != MAGIC
            || size.load(Ordering::Relaxed) != size_of::<T>() as u64
            || version.load(Ordering::Relaxed) != u64::from(LAYOUT_VERSION)
        {
            if !create {
                return Ok(None); // not written yet, or by another layout
            }
            // Fresh, or written by another layout: start empty.
            slot.word(3).store(0, Ordering::Relaxed);
            size.store(size_of::<T>() as u64, Ordering::Relaxed);
            version.store(u64::from(LAYOUT_VERSION), Ordering::Relaxed);
            magic.store(MAGIC, Ordering::Release);
        }
        Ok(Some(slot))
    }

    fn word(&self, i: usize) -> &AtomicU64 {
        // SAFETY: the header's first 8 words lie in the mapping, 8-byte aligned (page
        // aligned base); the mapping lives as long as self.
        unsafe { &*(self.map.add(8 * i) as *const AtomicU64) }
    }

    fn copy_ptr(&self, generation: u64) -> *mut T {
        let stride = size_of::<T>().next_multiple_of(64);
        // SAFETY: both copies lie within the mapping (len = HEADER + 2 strides).
        unsafe { self.map.add(HEADER + (generation % 2) as usize * stride) as *mut T }
    }

    /// The last sample stored, if any.
    pub fn load(&self) -> Option<T> {
        let generation = self.word(3).load(Ordering::Acquire);
        if generation == 0 {
            return None;
        }
        // SAFETY: the copy of generation `generation` was completely written before `generation` was
        // published (release/acquire); T is plain old data of the recorded size and
        // layout version, valid for any bit pattern of its f64/u64 fields.
        Some(unsafe { std::ptr::read_volatile(self.copy_ptr(generation)) })
    }

    /// The generation the next [`ResumeSlot::store`] publishes (its copy: the one not
    /// currently published).
    #[inline]
    fn next_generation(&self) -> u64 {
        self.word(3).load(Ordering::Relaxed) + 1
    }

    /// Asks for the cache lines the next [`ResumeSlot::store`] writes, for writing
    /// ([`crate::prefetch::lines_for_write`]): its copy and the generation word, which
    /// the launcher reads every 2 ms (a role's progress) from its own core.
    #[inline]
    pub fn prefetch_store(&self) {
        let generation = self.next_generation();
        // SAFETY: the copy lies within the mapping; it is only prefetched, never read.
        crate::prefetch::lines_for_write(unsafe {
            &*self.copy_ptr(generation).cast::<std::mem::MaybeUninit<T>>()
        });
        crate::prefetch::lines_for_write(self.word(3));
    }

    /// Stores `value` (allocation- and syscall-free).
    #[inline]
    pub fn store(&self, value: &T) {
        let generation = self.next_writable();
        // SAFETY: writes the copy not currently published; only this process writes.
        unsafe { std::ptr::write_volatile(self.copy_ptr(generation), *value) };
        fence(Ordering::Release);
        self.word(3).store(generation, Ordering::Release);
        self.mine.set(generation);
    }

    /// [`ResumeSlot::store`] of a value written in place: `write` is given the copy not
    /// currently published (it holds an older value: `write` sets every field), which is
    /// then published. A value assembled from parts (the controller's answer and its
    /// law's state) is written once, not built aside and copied.
    #[inline]
    pub fn store_with(&self, write: impl FnOnce(&mut T)) {
        let generation = self.next_writable();
        // SAFETY: the copy not currently published is only this process's to write; it
        // lies in the mapping, is aligned (page-aligned base, 64-byte stride) and holds
        // initialised bytes (a file's), and T is plain old data valid for any bit pattern
        // of its f64/u64 fields (as `load` reads it).
        write(unsafe { &mut *self.copy_ptr(generation) });
        fence(Ordering::Release);
        self.word(3).store(generation, Ordering::Release);
        self.mine.set(generation);
    }

    /// The generation the next store publishes, whose copy no [`Stored`] borrows.
    #[inline]
    fn next_writable(&self) -> u64 {
        assert!(self.lent.get() == 0, "a resume slot stored to while its value is borrowed");
        self.next_generation()
    }

    /// The value this process stored last, in place (the copy published), without a
    /// copy: the controller stores its answer with [`ResumeSlot::store_with`] and sends
    /// it from there. A store while it is borrowed panics (the store after next writes
    /// that copy). Before any store it holds whatever the file held.
    #[inline]
    pub fn stored(&self) -> Stored<'_, T> {
        let generation = self.mine.get();
        self.lent.set(self.lent.get() + 1);
        // SAFETY: the copy lies in the mapping, aligned, with initialised bytes, and T is
        // plain old data valid for any bit pattern (as in `store_with`). Only this
        // process writes the copies (the slot is its role's, owner-only), and not while
        // a `Stored` lives (`next_writable`), so nothing writes it under this borrow.
        let value = unsafe { &*self.copy_ptr(generation) };
        Stored { slot: self, value }
    }

    /// Forgets the stored sample (a finished run is not resumed).
    pub fn clear(&self) {
        self.word(3).store(0, Ordering::Release);
    }
}

impl<T: Copy + ZeroCopySend + Resumable> ResumeSlot<T> {
    /// The last sample stored, if a run of `ticks` ticks can continue from it
    /// ([`Resumable`]). One it cannot is forgotten (the role starts as a fresh one would)
    /// and `Err` says why, for the role to say and the launcher to list.
    pub fn load_checked(&self, ticks: u64) -> Result<Option<T>, String> {
        let Some(v) = self.load() else { return Ok(None) };
        match v.resume_fault(ticks) {
            None => Ok(Some(v)),
            Some(why) => {
                self.clear();
                Err(why)
            }
        }
    }

    /// [`Self::load_checked`] for `role` itself: a value it cannot continue from is
    /// refused with a line on stderr, and the role starts as a fresh one would (`None`).
    pub fn load_for(&self, role: &str, ticks: u64) -> Option<T> {
        self.load_checked(ticks).unwrap_or_else(|why| {
            eprintln!("{role}: resume slot refused ({why}); starting as a fresh {role}");
            None
        })
    }
}

/// What a role checks in its slot before it continues from it: like a received sample
/// (finite, plausible magnitudes, an attitude on SO(3)), and a tick within the run. A
/// slot is written only by its role's own user (owner-only, `crate::private`); this
/// guards the loop against a slot damaged all the same (a same-user process, a bug).
pub trait Resumable {
    /// Why a run of `ticks` ticks cannot continue from this stored value (`None`: it can).
    fn resume_fault(&self, ticks: u64) -> Option<String>;
}

/// The first of `fields` that is not finite or beyond ±`limit`, named.
pub fn unusable_field(fields: &[(&str, &[f64])], limit: f64) -> Option<String> {
    fields.iter().find_map(|(name, v)| {
        v.iter()
            .find(|x| !x.is_finite() || x.abs() > limit)
            .map(|x| format!("{name} has {x:e} (allowed: finite, within ±{limit:e})"))
    })
}

impl Resumable for StateSample {
    fn resume_fault(&self, ticks: u64) -> Option<String> {
        if self.tick > ticks {
            return Some(format!("tick {} is beyond the run's last tick {ticks}", self.tick));
        }
        if let Err(f) = self.validate() {
            return Some(f.to_string());
        }
        let applied_ok = self.applied_torque_tick == crate::wire::NO_TICK
            || self.applied_torque_tick <= self.tick;
        if !applied_ok {
            let (a, k) = (self.applied_torque_tick, self.tick);
            return Some(format!("applied_torque_tick {a} is after the state's tick {k}"));
        }
        unusable_field(
            &[
                ("t_s", &[self.t_s]),
                ("internal_h", &self.internal_h),
                ("internal_p", &self.internal_p),
                ("theta_rotor_rad", &self.theta_rotor_rad),
                ("applied_rotor_torque_nm", &self.applied_rotor_torque_nm),
                ("applied_body_torque_nm", &self.applied_body_torque_nm),
                ("rotor_work_j", &[self.rotor_work_j]),
            ],
            1e12,
        )
    }
}

impl<T: Copy + ZeroCopySend> Drop for ResumeSlot<T> {
    fn drop(&mut self) {
        // SAFETY: unmaps what open() mapped.
        unsafe { libc::munmap(self.map.cast(), self.len) };
    }
}

/// Removes every resume slot of a domain.
pub fn remove_slots(domain: &Domain) {
    let prefix = format!("{}resume_", domain.prefix());
    if let Ok(d) = std::fs::read_dir("/dev/shm") {
        for e in d.flatten() {
            if e.file_name().to_string_lossy().starts_with(&prefix) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::TorqueSample;

    #[test]
    fn a_damaged_state_is_refused_and_forgotten_and_a_good_one_kept() {
        use crate::wire::StateSample;
        let domain = Domain::new(&format!("slotchk{}", std::process::id())).expect("domain");
        let slot = ResumeSlot::<StateSample>::open(&domain, "plant").expect("open");
        // SAFETY: plain old data of f64 and u64 fields, valid all zero.
        let mut good: StateSample = unsafe { std::mem::zeroed() };
        good.tick = 10;
        good.r_row_major = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        good.applied_torque_tick = 9;
        slot.store(&good);
        assert_eq!(slot.load_checked(100).map(|s| s.map(|s| s.tick)), Ok(Some(10)));
        let mut damaged = [good; 4];
        damaged[0].r_row_major[0] = 2.0; // off SO(3)
        damaged[1].internal_h[1] = f64::NAN;
        damaged[2].tick = 101; // beyond the run
        damaged[3].applied_torque_tick = 11; // a torque from the future
        for (d, want) in damaged.iter().zip(["rotation", "internal_h", "beyond", "after"]) {
            slot.store(d);
            let why = slot.load_checked(100).expect_err("refused");
            assert!(why.contains(want), "{why}");
            assert!(slot.load().is_none(), "a refused state is forgotten");
        }
        drop(slot);
        remove_slots(&domain);
    }

    #[test]
    fn a_slot_returns_the_last_stored_sample_across_reopen() {
        let domain = Domain::new(&format!("slot{}", std::process::id())).expect("domain");
        let mut t = TorqueSample {
            rotor_torque_nm: [1.0, 2.0, 3.0],
            body_torque_nm: [0.5; 3],
            ..Default::default()
        };
        {
            let slot = ResumeSlot::<TorqueSample>::open(&domain, "controller").expect("open");
            assert!(slot.load().is_none());
            for k in 0..5 {
                t.tick = k;
                slot.store(&t);
            }
        }
        let slot = ResumeSlot::<TorqueSample>::open(&domain, "controller").expect("reopen");
        assert_eq!(slot.load().map(|s| s.tick), Some(4));
        slot.clear();
        assert!(slot.load().is_none());
        drop(slot);
        remove_slots(&domain);
        assert!(!ResumeSlot::<TorqueSample>::path(&domain, "controller").exists());
    }

    /// The value stored last is read in place, as stored (each store alternates between
    /// the two copies), and a store while it is borrowed panics rather than write the
    /// copy under the borrow.
    #[test]
    fn the_value_stored_last_is_borrowed_in_place_and_no_store_writes_under_it() {
        let domain = Domain::new(&format!("slotin{}", std::process::id())).expect("domain");
        let slot = ResumeSlot::<TorqueSample>::open(&domain, "controller").expect("open");
        for k in 1..=3 {
            slot.store_with(|t| *t = TorqueSample { tick: k, ..Default::default() });
            let stored = slot.stored();
            assert_eq!((stored.tick, slot.load().map(|s| s.tick)), (k, Some(k)));
        }
        // What this process stored, whatever the file's word says now (another process
        // could change it: here, a clear).
        slot.clear();
        assert_eq!(slot.stored().tick, 3);
        let stored = slot.stored();
        let again = slot.stored(); // two borrows: the first one's end does not end both
        drop(stored);
        let store = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| slot.store(&*again)));
        assert!(store.is_err(), "a store while the value is borrowed must panic");
        assert_eq!(again.tick, 3, "the borrowed value is unchanged");
        drop(again);
        slot.store(&TorqueSample { tick: 4, ..Default::default() });
        assert_eq!(slot.stored().tick, 4);
        drop(slot);
        remove_slots(&domain);
    }
}
