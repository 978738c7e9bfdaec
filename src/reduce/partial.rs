//! What one piece of a reduced trace leaves for the others to be folded into.

use std::collections::BTreeMap;

/// A piece's reduction, or several pieces' folded in ray order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Partial {
    /// Counters that add up.
    Sums(Vec<u64>),
    /// Counters that add up, few of them set: `(index, count)` by ascending index, of `len` counters. A piece's
    /// histogram, whose bins (up to [`super::MAX_HISTOGRAM_BINS`]) may far outnumber its hits: a piece of 1,024 rays
    /// then keeps its few counts, not megabytes of zeros.
    SparseSums {
        /// Counters in all (those not listed are 0).
        len: usize,
        /// The counters set, by ascending index.
        counts: Vec<(u32, u64)>,
    },
    /// Counters by id that add up.
    Keyed(BTreeMap<i32, u64>),
    /// Records in ray order that concatenate, and the items left out so far.
    Ordered {
        /// The records.
        bytes: Vec<u8>,
        /// Items that could not be encoded.
        dropped: u64,
    },
}

/// Most counters a [`Partial::SparseSums`] of `len` keeps set before it becomes [`Partial::Sums`]: the counters'
/// memory stays within a sixteenth of theirs, and a fold of many pieces merges short lists.
const fn most_sparse(len: usize) -> usize {
    len / 64
}

impl Partial {
    /// `len` counters, the counter of each of `slots` (indices below `len`, at most `most_slots` of them) counted
    /// once: all the counters where they take no more room than the slots could (counted in place), or where the
    /// slots are many for the counters; listed otherwise ([`Partial::SparseSums`]).
    pub fn counted(len: usize, slots: impl Iterator<Item = u32>, most_slots: usize) -> Partial {
        if len <= most_slots {
            return all_counted(len, slots);
        }
        let mut slots: Vec<u32> = slots.collect();
        if slots.len() > most_sparse(len) {
            return all_counted(len, slots.into_iter());
        }
        slots.sort_unstable();
        let mut counts: Vec<(u32, u64)> = Vec::new();
        for slot in slots {
            match counts.last_mut() {
                Some((last, count)) if *last == slot => *count += 1,
                _ => counts.push((slot, 1)),
            }
        }
        Partial::SparseSums { len, counts }
    }

    /// Folds `next` (the partial of the rays right after this one's) into this one.
    ///
    /// # Panics
    /// If the two are of different kinds (they come from one reduction).
    pub fn merge(&mut self, next: Partial) {
        match (self, next) {
            (Partial::Sums(sums), Partial::Sums(more)) => {
                sums.iter_mut().zip(more).for_each(|(sum, more)| *sum += more)
            }
            (Partial::Sums(sums), Partial::SparseSums { counts, .. }) => {
                counts.into_iter().for_each(|(index, count)| sums[index as usize] += count)
            }
            (this @ Partial::SparseSums { .. }, Partial::Sums(mut more)) => {
                let Partial::SparseSums { counts, .. } = std::mem::replace(this, Partial::Sums(Vec::new())) else {
                    unreachable!("matched above")
                };
                counts.into_iter().for_each(|(index, count)| more[index as usize] += count);
                *this = Partial::Sums(more);
            }
            (this @ Partial::SparseSums { .. }, Partial::SparseSums { counts: more, .. }) => {
                let Partial::SparseSums { len, counts } = std::mem::replace(this, Partial::Sums(Vec::new())) else {
                    unreachable!("matched above")
                };
                *this = merged_counts(len, counts, more);
            }
            (Partial::Keyed(counts), Partial::Keyed(more)) => {
                for (id, count) in more {
                    *counts.entry(id).or_insert(0) += count;
                }
            }
            (Partial::Ordered { bytes, dropped }, Partial::Ordered { bytes: more, dropped: more_dropped }) => {
                // The first piece's records are taken as they are (on a GPU, a whole image is one piece), unless
                // room was made for them ([`Partial::merge_all`]).
                if bytes.is_empty() && bytes.capacity() < more.len() {
                    *bytes = more;
                } else {
                    bytes.extend_from_slice(&more);
                }
                *dropped += more_dropped;
            }
            (this, next) => panic!("partials of different reductions: {this:?} and {next:?}"),
        }
    }
    /// Folds `parts` (the partials of the rays right after this one's, in order) into this one: [`Partial::merge`]
    /// of each in turn, with room made once for the records of all but the first (which an empty partial takes as
    /// they are: a trace of one piece, as a GPU image is, is folded without copying its records).
    pub fn merge_all(&mut self, parts: Vec<Partial>) {
        let records = |part: &Partial| if let Partial::Ordered { bytes, .. } = part { bytes.len() } else { 0 };
        let rest: usize = parts.iter().skip(1).map(records).sum();
        let mut parts = parts.into_iter();
        if let Some(first) = parts.next() {
            self.merge(first);
        }
        if let Partial::Ordered { bytes, .. } = self {
            bytes.reserve_exact(rest);
        }
        for part in parts {
            self.merge(part);
        }
    }
}

/// `len` counters, the counter of each of `slots` counted once, all of them ([`Partial::Sums`]).
fn all_counted(len: usize, slots: impl Iterator<Item = u32>) -> Partial {
    let mut sums = vec![0u64; len];
    slots.for_each(|slot| sums[slot as usize] += 1);
    Partial::Sums(sums)
}

/// The counters of two [`Partial::SparseSums`] of `len` added up: listed while they stay few, all of them once
/// they do not.
fn merged_counts(len: usize, a: Vec<(u32, u64)>, b: Vec<(u32, u64)>) -> Partial {
    let mut counts = Vec::with_capacity(a.len() + b.len());
    let (mut a, mut b) = (a.into_iter().peekable(), b.into_iter().peekable());
    loop {
        let next = match (a.peek(), b.peek()) {
            (Some(&(i, x)), Some(&(j, y))) if i == j => {
                a.next();
                b.next();
                (i, x + y)
            }
            (Some(&(i, _)), Some(&(j, _))) if j < i => b.next().expect("peeked"),
            (Some(_), _) => a.next().expect("peeked"),
            (None, Some(_)) => b.next().expect("peeked"),
            (None, None) => break,
        };
        counts.push(next);
    }
    if counts.len() <= most_sparse(len) {
        return Partial::SparseSums { len, counts };
    }
    let mut sums = vec![0u64; len];
    counts.into_iter().for_each(|(index, count)| sums[index as usize] = count);
    Partial::Sums(sums)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ordered_records_concatenate_and_the_first_are_taken_without_a_copy() {
        let first = vec![1u8, 2, 3];
        let at = first.as_ptr();
        let mut folded = Partial::Ordered { bytes: Vec::new(), dropped: 0 };
        folded.merge(Partial::Ordered { bytes: first, dropped: 1 });
        let Partial::Ordered { bytes, .. } = &folded else { unreachable!() };
        assert_eq!(bytes.as_ptr(), at, "the first piece's records were copied");
        folded.merge(Partial::Ordered { bytes: vec![4, 5], dropped: 2 });
        assert_eq!(folded, Partial::Ordered { bytes: vec![1, 2, 3, 4, 5], dropped: 3 });
    }

    #[test]
    fn merged_all_at_once_they_fill_the_room_made_for_them() {
        let parts = vec![
            Partial::Ordered { bytes: vec![1, 2, 3], dropped: 1 },
            Partial::Ordered { bytes: vec![4], dropped: 2 },
        ];
        let mut folded = Partial::Ordered { bytes: Vec::new(), dropped: 0 };
        folded.merge_all(parts);
        let Partial::Ordered { bytes, .. } = &folded else { unreachable!() };
        assert_eq!(bytes.capacity(), 4, "sized once");
        assert_eq!(folded, Partial::Ordered { bytes: vec![1, 2, 3, 4], dropped: 3 });
        // One part alone (a GPU image) is taken as it is.
        let only = vec![7u8; 5];
        let at = only.as_ptr();
        let mut folded = Partial::Ordered { bytes: Vec::new(), dropped: 0 };
        folded.merge_all(vec![Partial::Ordered { bytes: only, dropped: 0 }]);
        let Partial::Ordered { bytes, .. } = &folded else { unreachable!() };
        assert_eq!(bytes.as_ptr(), at, "the only part's records were copied");
        let mut sums = Partial::Sums(vec![1, 2]);
        sums.merge_all(vec![Partial::Sums(vec![3, 4]), Partial::Sums(vec![5, 6])]);
        assert_eq!(sums, Partial::Sums(vec![9, 12]));
    }

    /// The counts of `slots` among `len` counters, all of them.
    fn dense(len: usize, slots: &[u32]) -> Vec<u64> {
        let mut sums = vec![0; len];
        slots.iter().for_each(|&slot| sums[slot as usize] += 1);
        sums
    }

    #[test]
    fn few_counts_of_many_counters_are_listed_and_fold_in_any_order_into_the_same_sums() {
        let len = 1 << 20;
        // Pieces of up to 1,024 slots (a histogram's piece of 1,024 rays), and one of more than a sixty-fourth of
        // the counters, which is counted whole.
        let pieces: Vec<Vec<u32>> = (0..40u32)
            .map(|piece| {
                let slots = if piece == 7 { 20_000 } else { 1 + piece * 25 };
                (0..slots).map(|i| (i * 7919 + piece * 104_729) % len as u32 / (1 + piece % 3)).collect()
            })
            .collect();
        let partials: Vec<Partial> =
            pieces.iter().map(|slots| Partial::counted(len, slots.iter().copied(), slots.len())).collect();
        for (slots, partial) in pieces.iter().zip(&partials) {
            match partial {
                Partial::SparseSums { counts, .. } => {
                    assert!(slots.len() <= most_sparse(len) && counts.len() <= slots.len());
                    assert!(counts.windows(2).all(|pair| pair[0].0 < pair[1].0), "listed by ascending index");
                }
                Partial::Sums(sums) => assert!(slots.len() > most_sparse(len) && sums.len() == len),
                other => panic!("{other:?}"),
            }
        }
        let every: Vec<u32> = pieces.concat();
        let expected = Partial::Sums(dense(len, &every));
        let as_sums = |partial: Partial| match partial {
            Partial::SparseSums { len, counts } => {
                let mut sums = vec![0; len];
                counts.into_iter().for_each(|(index, count)| sums[index as usize] = count);
                Partial::Sums(sums)
            }
            sums => sums,
        };
        // In order, backwards, and the large piece last, from an empty list.
        let mut orders: Vec<Vec<usize>> = vec![(0..40).collect(), (0..40).rev().collect()];
        orders.push((0..40).filter(|&i| i != 7).chain([7]).collect());
        for order in orders {
            let mut folded = Partial::SparseSums { len, counts: Vec::new() };
            for &piece in &order {
                folded.merge(partials[piece].clone());
            }
            assert_eq!(as_sums(folded), expected, "folded in the order {order:?}");
        }
        // Listed counts that grow many become all the counters.
        let mut few = Partial::counted(len, 0..16_000, 16_000);
        few.merge(Partial::counted(len, 16_000..32_000, 16_000));
        assert!(matches!(few, Partial::Sums(_)));
        assert_eq!(few, Partial::Sums(dense(len, &(0..32_000).collect::<Vec<_>>())));
    }
}
