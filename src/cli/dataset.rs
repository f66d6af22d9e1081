//! `nak dataset join`: the shards of a dataset made on many machines, checked and assembled.

use std::path::PathBuf;

use anyhow::Context;
use nak::data::join;

#[derive(clap::Args)]
pub struct JoinArgs {
    /// Where the whole dataset goes (a new or empty directory).
    #[arg(long)]
    pub out: PathBuf,
    /// Every shard's directory, as `nak datagen --shard I/N --out DIR` wrote them (any order).
    #[arg(required = true)]
    pub shards: Vec<PathBuf>,
}

pub fn join(args: &JoinArgs) -> anyhow::Result<()> {
    let joined = join::join(&args.shards, &args.out)
        .with_context(|| format!("cannot join {} shards into {}", args.shards.len(), args.out.display()))?;
    println!(
        "{}: {} samples ({} single, {} multi) in {} chunks from {} shards",
        args.out.display(),
        joined.info.total(),
        joined.info.single,
        joined.info.multi,
        joined.chunks,
        args.shards.len()
    );
    Ok(())
}
