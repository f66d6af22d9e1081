//! Datasets made in shards on many machines: which chunks a shard owns.
//!
//! Shard I of N owns the chunks c with c mod N = I (so every shard gets a fair mix of single- and
//! two-grasper samples) and writes them, under their global chunk numbers, into a directory of its
//! own whose `dataset.json` names the shard. [`super::join::join`] assembles the shards into the dataset
//! one machine would make.

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
