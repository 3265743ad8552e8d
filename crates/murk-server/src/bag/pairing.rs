//! Pairs the messages of two topics by their header stamps: a left image with its right image,
//! an amplitude image with its phase image. Bags are written in log-time order, so a message
//! whose partner has not come within the tolerance by the time a later pair forms never will:
//! it is given up as unpaired (and reported), and memory stays bounded.

use std::collections::VecDeque;

/// Which of the two topics a message came on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    /// The first topic (left, amplitude).
    First,
    /// The second topic (right, phase).
    Second,
}

/// A message given up without a partner.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Unpaired {
    /// Its topic.
    pub side: Side,
    /// Its header stamp, nanoseconds.
    pub stamp_ns: u64,
}

/// Pairs two stamped streams within a tolerance.
#[derive(Debug)]
pub struct StampPairer<T> {
    tolerance_ns: u64,
    capacity: usize,
    first: VecDeque<(u64, T)>,
    second: VecDeque<(u64, T)>,
    unpaired: Vec<Unpaired>,
}

impl<T> StampPairer<T> {
    /// Pairs stamps at most `tolerance_ns` apart, holding at most `capacity` messages per side
    /// while they wait.
    pub fn new(tolerance_ns: u64, capacity: usize) -> Self {
        Self {
            tolerance_ns,
            capacity: capacity.max(1),
            first: VecDeque::new(),
            second: VecDeque::new(),
            unpaired: Vec::new(),
        }
    }

    /// Adds a message; returns a pair (first, second, the first's stamp) when it completes one.
    pub fn push(&mut self, side: Side, stamp_ns: u64, item: T) -> Option<(T, T, u64)> {
        let tol = self.tolerance_ns;
        let (own, other) = match side {
            Side::First => (&mut self.first, &mut self.second),
            Side::Second => (&mut self.second, &mut self.first),
        };
        let best = other
            .iter()
            .enumerate()
            .filter(|(_, (s, _))| s.abs_diff(stamp_ns) <= tol)
            .min_by_key(|(_, (s, _))| s.abs_diff(stamp_ns))
            .map(|(i, _)| i);
        let Some(i) = best else {
            own.push_back((stamp_ns, item));
            if own.len() > self.capacity {
                let (s, _) = own.pop_front().expect("a full queue");
                self.unpaired.push(Unpaired { side, stamp_ns: s });
            }
            return None;
        };
        let (other_stamp, partner) = other.remove(i).expect("an index found above");
        // What waits on either side from before this pair has missed its chance.
        let cutoff = stamp_ns.min(other_stamp).saturating_sub(tol);
        let other_side = match side {
            Side::First => Side::Second,
            Side::Second => Side::First,
        };
        for (queue, s) in [(own, side), (other, other_side)] {
            while queue.front().is_some_and(|(t, _)| *t < cutoff) {
                let (t, _) = queue.pop_front().expect("checked");
                self.unpaired.push(Unpaired {
                    side: s,
                    stamp_ns: t,
                });
            }
        }
        Some(match side {
            Side::First => (item, partner, stamp_ns),
            Side::Second => (partner, item, other_stamp),
        })
    }

    /// Messages given up since the last call.
    pub fn take_unpaired(&mut self) -> Vec<Unpaired> {
        std::mem::take(&mut self.unpaired)
    }

    /// Gives up every waiting message (at the end of the bag).
    pub fn finish(&mut self) -> Vec<Unpaired> {
        let mut out = self.take_unpaired();
        for (queue, side) in [
            (&mut self.first, Side::First),
            (&mut self.second, Side::Second),
        ] {
            out.extend(
                queue
                    .drain(..)
                    .map(|(stamp_ns, _)| Unpaired { side, stamp_ns }),
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn pairs_within_the_tolerance_whichever_side_comes_first() {
        let mut p = StampPairer::new(1_000, 8);
        assert_eq!(p.push(Side::Second, 10_000, "r0"), None);
        assert_eq!(
            p.push(Side::First, 10_400, "l0"),
            Some(("l0", "r0", 10_400))
        );
        assert_eq!(p.push(Side::First, 20_000, "l1"), None);
        assert_eq!(
            p.push(Side::Second, 20_900, "r1"),
            Some(("l1", "r1", 20_000))
        );
        assert!(p.finish().is_empty());
    }

    #[test]
    fn a_dropped_message_is_reported_once_a_later_pair_forms() {
        let mut p = StampPairer::new(1_000, 8);
        p.push(Side::First, 10_000, 0);
        // the right image of 10_000 never came
        p.push(Side::First, 20_000, 1);
        assert_eq!(p.push(Side::Second, 20_000, 1), Some((1, 1, 20_000)));
        assert_eq!(
            p.take_unpaired(),
            vec![Unpaired {
                side: Side::First,
                stamp_ns: 10_000
            }]
        );
    }

    #[test]
    fn the_nearest_partner_is_chosen() {
        let mut p = StampPairer::new(5_000, 8);
        p.push(Side::Second, 10_000, "far");
        p.push(Side::Second, 13_000, "near");
        assert_eq!(
            p.push(Side::First, 14_000, "l"),
            Some(("l", "near", 14_000))
        );
        assert_eq!(p.finish().len(), 1);
    }

    proptest! {
        /// Every message is paired or reported, never both, never lost; waiting stays bounded.
        #[test]
        fn every_message_is_accounted_for(
            events in prop::collection::vec((any::<bool>(), 0u64..100), 0..200),
        ) {
            let mut p = StampPairer::new(3, 4);
            let mut t = 0u64;
            let mut paired = 0usize;
            for (k, (first, dt)) in events.iter().enumerate() {
                t += dt;
                let side = if *first { Side::First } else { Side::Second };
                if let Some((a, b, _)) = p.push(side, t, k) {
                    prop_assert_ne!(a, b);
                    paired += 2;
                }
                prop_assert!(p.first.len() <= 4 && p.second.len() <= 4);
            }
            let unpaired = p.finish().len();
            prop_assert_eq!(paired + unpaired, events.len());
        }
    }
}
