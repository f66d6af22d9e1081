//! Datasets made in parts: which chunks a shard owns, and which a run makes.
//!
//! Shard I of N owns the chunks c with c mod N = I (so every shard gets a fair mix of single- and
//! two-grasper samples) and writes them, under their global chunk numbers, into a directory of its
//! own whose `dataset.json` names the shard. [`super::join::join`] assembles the shards into the dataset
//! one machine would make.
//!
//! A [`ChunkRange`] is a run's part of a set, not the set's: the run makes only those chunks, and the
//! set (its `dataset.json`) is the whole one, so chunks made elsewhere with the same arguments are
//! copied in beside them and a later run without a range makes the rest.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

/// Shard `index` of `count` (0-based).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Shard {
    pub fn owns(&self, chunk: usize) -> bool {
        chunk % self.count == self.index
    }
}

impl fmt::Display for Shard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl FromStr for Shard {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let malformed = || format!("{text:?} is not a shard: write I/N, shard I (0-based) of N");
        let (index, count) = text.split_once('/').ok_or_else(malformed)?;
        let index: usize = index.trim().parse().map_err(|_| malformed())?;
        let count: usize = count.trim().parse().map_err(|_| malformed())?;
        if count == 0 {
            return Err(format!("{text:?}: a dataset is split into at least one shard"));
        }
        if index >= count {
            return Err(format!(
                "{text:?}: shards are numbered from 0, so shard {index} does not exist among {count} (0/{count} to {}/{count})",
                count - 1
            ));
        }
        Ok(Self { index, count })
    }
}

/// Chunks `first` to `last`, both included (`nak datagen --chunks FIRST-LAST`, or `N` for one).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChunkRange {
    pub first: usize,
    pub last: usize,
}

impl ChunkRange {
    pub fn contains(&self, chunk: usize) -> bool {
        (self.first..=self.last).contains(&chunk)
    }

    /// Refuses a range that reaches past a set of `chunks` chunks.
    pub fn check_within(&self, chunks: usize) -> Result<(), String> {
        if self.last >= chunks {
            return Err(format!(
                "--chunks {self}: the set has {chunks} chunks, numbered 0 to {}",
                chunks.saturating_sub(1)
            ));
        }
        Ok(())
    }
}

impl fmt::Display for ChunkRange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}-{}", self.first, self.last)
    }
}

impl FromStr for ChunkRange {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let malformed = || format!("{text:?} is not a chunk range: write FIRST-LAST (0-based, both made) or N");
        let (first, last) = text.split_once('-').unwrap_or((text, text));
        let first: usize = first.trim().parse().map_err(|_| malformed())?;
        let last: usize = last.trim().parse().map_err(|_| malformed())?;
        if last < first {
            return Err(format!("{text:?}: the last chunk comes before the first"));
        }
        Ok(Self { first, last })
    }
}
