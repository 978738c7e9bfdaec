//! What one piece of a reduced trace leaves for the others to be folded into.

use std::collections::BTreeMap;

/// A piece's reduction, or several pieces' folded in ray order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Partial {
    /// Counters that add up.
    Sums(Vec<u64>),
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

impl Partial {
    /// Folds `next` (the partial of the rays right after this one's) into this one.
    ///
    /// # Panics
    /// If the two are of different kinds (they come from one reduction).
    pub fn merge(&mut self, next: Partial) {
        match (self, next) {
            (Partial::Sums(sums), Partial::Sums(more)) => {
                sums.iter_mut().zip(more).for_each(|(sum, more)| *sum += more)
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
}
