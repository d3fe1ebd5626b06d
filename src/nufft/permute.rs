//! Moving point values between the caller's order and the plan's (tile) order.
//!
//! The plan walks points tile by tile, so in the caller's order its reads (gridding) or writes
//! (degridding) would land anywhere in an array of `16 n` bytes: a cache and TLB miss each,
//! which costs as much as the gridding arithmetic itself. Instead values go through a buffer
//! of "slots" grouped by *part*, a block of `2^shift` consecutive caller indices (a few
//! hundred KiB of values):
//!
//! * between the caller's array and the slots, each part is handled on its own, so the
//!   random accesses stay inside one part's block, in cache;
//! * between the slots and the gridding loops, each task reads (or writes) its own segment
//!   of every part sequentially, one cursor per part, in plan order.
//!
//! Slots are laid out part by part; inside a part, task by task; inside a task's segment, in
//! plan order. Every segment is a disjoint slice, so all of this is parallel without unsafe.

use num_complex::Complex64;
use rayon::prelude::*;
use std::ops::Range;

/// Largest part, in points (`2^15` complex values = 512 KiB), unless there would be more
/// than [`MAX_PARTS`] parts.
const PART_SHIFT: u32 = 15;
const MAX_PARTS: usize = 256;

/// The plan's order against the caller's, organised by parts (see the module docs).
#[derive(Clone, Debug, Default)]
pub(crate) struct Permutation {
    /// A caller index `i` is in part `i >> shift`.
    pub shift: u32,
    nparts: usize,
    ntasks: usize,
    /// `bounds[j * nparts + p]`: first slot of task `j`'s segment of part `p`; row `ntasks`
    /// holds the parts' ends.
    bounds: Vec<usize>,
    /// Per slot, the caller index minus its part's first index.
    local: Vec<u32>,
}

impl Permutation {
    /// `order[k]`: caller index of plan point `k`; `tasks`: consecutive ranges of plan points
    /// covering `0 .. order.len()`, each handled by one task.
    pub fn new(order: &[u32], tasks: &[Range<usize>]) -> Permutation {
        let n = order.len();
        let mut shift = PART_SHIFT;
        while (n >> shift) >= MAX_PARTS {
            shift += 1;
        }
        let nparts = n.div_ceil(1 << shift).max(1);
        let ntasks = tasks.len();
        let counts: Vec<Vec<usize>> = tasks
            .par_iter()
            .map(|range| {
                let mut counts = vec![0usize; nparts];
                for &i in &order[range.clone()] {
                    counts[(i >> shift) as usize] += 1;
                }
                counts
            })
            .collect();
        let mut bounds = vec![0usize; (ntasks + 1) * nparts];
        for p in 0..nparts {
            let mut slot = p << shift;
            for (j, counts) in counts.iter().enumerate() {
                bounds[j * nparts + p] = slot;
                slot += counts[p];
            }
            bounds[ntasks * nparts + p] = slot;
        }
        let mut perm = Permutation { shift, nparts, ntasks, bounds, local: Vec::new() };
        let mut local = vec![0u32; n];
        let mask = (1u32 << shift) - 1;
        perm.task_segments_mut(&mut local).into_par_iter().zip(tasks.par_iter()).for_each(|(mut segs, range)| {
            let mut cursor = vec![0usize; nparts];
            for &i in &order[range.clone()] {
                let p = (i >> shift) as usize;
                segs[p][cursor[p]] = i & mask;
                cursor[p] += 1;
            }
        });
        perm.local = local;
        perm
    }

    /// Number of parts.
    #[cfg(test)]
    pub fn parts(&self) -> usize {
        self.nparts
    }

    /// The part-major slot buffer `slots` cut into each task's segments: `result[j][p]`.
    pub fn task_segments_mut<'a, T>(&self, slots: &'a mut [T]) -> Vec<Vec<&'a mut [T]>> {
        let mut segs: Vec<Vec<&'a mut [T]>> = (0..self.ntasks).map(|_| Vec::with_capacity(self.nparts)).collect();
        let mut rest = slots;
        for p in 0..self.nparts {
            for (j, task_segs) in segs.iter_mut().enumerate() {
                let len = self.bounds[(j + 1) * self.nparts + p] - self.bounds[j * self.nparts + p];
                let (seg, tail) = std::mem::take(&mut rest).split_at_mut(len);
                task_segs.push(seg);
                rest = tail;
            }
        }
        segs
    }

    /// Like [`Permutation::task_segments_mut`], shared.
    pub fn task_segments<'a, T>(&self, slots: &'a [T]) -> Vec<Vec<&'a [T]>> {
        let mut segs: Vec<Vec<&'a [T]>> = (0..self.ntasks).map(|_| Vec::with_capacity(self.nparts)).collect();
        let mut rest = slots;
        for p in 0..self.nparts {
            for (j, task_segs) in segs.iter_mut().enumerate() {
                let len = self.bounds[(j + 1) * self.nparts + p] - self.bounds[j * self.nparts + p];
                let (seg, tail) = rest.split_at(len);
                task_segs.push(seg);
                rest = tail;
            }
        }
        segs
    }

    /// Slots from values in the caller's order, in parallel (a slot's value comes from its
    /// own part's block, which stays in cache while the slots of the part are filled).
    pub fn gather(&self, values: &[Complex64]) -> Vec<Complex64> {
        let shift = self.shift;
        self.local.par_iter().enumerate().map(|(s, &l)| values[((s >> shift) << shift) + l as usize]).collect()
    }

    /// Values in the caller's order from slots, part by part in parallel.
    pub fn scatter(&self, slots: &[Complex64], values: &mut [Complex64]) {
        let part = 1 << self.shift;
        values.par_chunks_mut(part).zip(self.local.par_chunks(part)).zip(slots.par_chunks(part)).for_each(
            |((values, local), slots)| {
                for (&s, &l) in slots.iter().zip(local) {
                    values[l as usize] = s;
                }
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_through_slots_and_segments() {
        // A scrambled order over several parts, split into uneven tasks.
        let n = 3 * (1 << PART_SHIFT) + 1234;
        let order: Vec<u32> = (0..n as u64).map(|k| ((k * 7919 + 13) % n as u64) as u32).collect();
        let tasks = vec![0..10, 10..50_000, 50_000..50_001, 50_001..n];
        let perm = Permutation::new(&order, &tasks);
        assert_eq!(perm.parts(), 4);
        let values: Vec<Complex64> = (0..n).map(|i| Complex64::new(i as f64, -(i as f64))).collect();
        let slots = perm.gather(&values);
        // Each task reads its points' values in plan order, one cursor per part.
        let segs = perm.task_segments(&slots);
        for (range, segs) in tasks.iter().zip(&segs) {
            let mut cursor = vec![0; perm.parts()];
            for &i in &order[range.clone()] {
                let p = (i >> perm.shift) as usize;
                assert_eq!(segs[p][cursor[p]], values[i as usize]);
                cursor[p] += 1;
            }
        }
        // And written the same way, they come back to the caller's order.
        let mut slots2 = vec![Complex64::default(); n];
        for (range, mut segs) in tasks.iter().zip(perm.task_segments_mut(&mut slots2)) {
            let mut cursor = vec![0; perm.parts()];
            for &i in &order[range.clone()] {
                let p = (i >> perm.shift) as usize;
                segs[p][cursor[p]] = values[i as usize] * 2.0;
                cursor[p] += 1;
            }
        }
        let mut back = vec![Complex64::default(); n];
        perm.scatter(&slots2, &mut back);
        assert!(back.iter().zip(&values).all(|(b, v)| *b == v * 2.0));
    }
}
