//! Shards joined into the dataset one machine would make. Every sample is drawn from (seed, index),
//! so a chunk is the same bytes whichever machine solved it; [`join`] checks that the shards belong
//! together and are complete, and assembles the whole.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::dataset::{self, DatasetError, DatasetInfo};

/// What joining did.
#[derive(Debug, Clone, PartialEq)]
pub struct Joined {
    pub info: DatasetInfo,
    pub chunks: usize,
}

/// Checks that `shards` are every shard of one dataset, each complete, and writes that dataset to
/// `out` (which must be empty or not exist): the same files an unsharded `nak datagen` writes.
/// Chunk files are hard-linked where the file system allows, else copied.
pub fn join(shards: &[PathBuf], out: &Path) -> Result<Joined, DatasetError> {
    let first = shards
        .first()
        .ok_or_else(|| dataset::format(out, "no shard directories given"))?;
    if out.exists() && std::fs::read_dir(out).map_err(dataset::io(out))?.next().is_some() {
        return Err(dataset::format(
            out,
            "is not empty: the joined dataset goes into a new directory",
        ));
    }
    let mut whole: Option<(DatasetInfo, &Path)> = None;
    let mut by_index: BTreeMap<usize, &Path> = BTreeMap::new();
    for dir in shards {
        let info = dataset::read_info(dir)?;
        let shard = info.shard.ok_or_else(|| {
            dataset::format(
                &dir.join("dataset.json"),
                "is a whole dataset, not a shard (made without --shard)",
            )
        })?;
        let unsharded = DatasetInfo { shard: None, ..info };
        match &whole {
            None => whole = Some((unsharded.clone(), dir)),
            Some((expected, expected_dir)) if *expected != unsharded => {
                return Err(dataset::format(
                    &dir.join("dataset.json"),
                    format!(
                        "shard {shard} belongs to another dataset than {} ({}); shards join only when \
                         mesh, regime, seed, sizes, chunk size, solver settings, volumetric law and nak \
                         version agree",
                        expected_dir.display(),
                        dataset::differences(&unsharded, expected)
                    ),
                ));
            }
            Some(_) => {}
        }
        if let Some(other) = by_index.insert(shard.index, dir) {
            return Err(dataset::format(
                dir,
                format!("shard {shard} is given twice (also {})", other.display()),
            ));
        }
        // N directories with distinct indices below N are every shard exactly once.
        if shard.count != shards.len() {
            return Err(dataset::format(
                dir,
                format!(
                    "is shard {shard}: all {} shards are needed, {} directories were given",
                    shard.count,
                    shards.len()
                ),
            ));
        }
        let missing: Vec<usize> = (0..unsharded.chunks())
            .filter(|&c| shard.owns(c) && !dataset::chunk_paths(dir, c).1.is_file())
            .collect();
        if !missing.is_empty() {
            return Err(dataset::format(
                dir,
                format!(
                    "shard {shard} is incomplete: chunks {missing:?} are not written yet; run its \
                     nak datagen --shard {shard} again to finish them"
                ),
            ));
        }
    }
    let (info, _) = whole.ok_or_else(|| dataset::format(first, "no shard directories given"))?;
    let mesh_bytes =
        std::fs::read(first.join("mesh.safetensors")).map_err(dataset::io(&first.join("mesh.safetensors")))?;
    for dir in shards {
        let path = dir.join("mesh.safetensors");
        if !dataset::same_mesh_file(&std::fs::read(&path).map_err(dataset::io(&path))?, &mesh_bytes) {
            return Err(dataset::format(
                &path,
                format!("differs from {}'s mesh", first.display()),
            ));
        }
    }
    dataset::write_info(out, &info)?;
    let mesh_path = out.join("mesh.safetensors");
    std::fs::write(&mesh_path, &mesh_bytes).map_err(dataset::io(&mesh_path))?;
    for chunk in 0..info.chunks() {
        let dir = by_index[&(chunk % shards.len())];
        let (from, to) = (dataset::chunk_paths(dir, chunk), dataset::chunk_paths(out, chunk));
        // The tensors first, the JSON (which marks a chunk complete) last, as datagen writes them.
        // A nonlinear chunk's path states (written before its JSON too), where it has them.
        let path_states = Some((
            dataset::path_states_path(dir, chunk),
            dataset::path_states_path(out, chunk),
        ))
        .filter(|(source, _)| source.is_file());
        for (source, target) in [(from.0, to.0)].into_iter().chain(path_states).chain([(from.1, to.1)]) {
            if std::fs::hard_link(&source, &target).is_err() {
                std::fs::copy(&source, &target).map_err(dataset::io(&source))?;
            }
        }
    }
    Ok(Joined {
        chunks: info.chunks(),
        info,
    })
}
