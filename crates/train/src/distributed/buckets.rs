//! Gradient averaging in buckets, as DDP does: the gradients, in reverse
//! parameter order (about the order the backward finishes them), are packed
//! into flat f32 buckets of at most `BRIDGEV2W_BUCKET_MB` each and
//! sum-all-reduced one after the other (the backend may overlap one bucket's
//! reduction with packing the next), so the extra memory is a bucket or two,
//! not a second copy of every gradient. Before the buckets, one small
//! all-gather of every rank's gradient layout and loss values checks that
//! the ranks agree (a mismatch stops every rank with the same error, naming
//! the ranks and values) and averages the losses.

use super::Collective;
use crate::{Result, TrainError};
use tch::{Kind, Tensor};

/// The gradients `0..numels.len()` packed into buckets of at most
/// `cap_bytes` (4-byte values), in reverse order; a gradient larger than
/// the cap is a bucket of its own. Each bucket lists its gradients' indices.
pub fn bucket_ranges(numels: &[usize], cap_bytes: usize) -> Vec<Vec<usize>> {
    let cap = (cap_bytes / 4).max(1);
    let mut buckets: Vec<Vec<usize>> = Vec::new();
    let mut current: Vec<usize> = Vec::new();
    let mut filled = 0usize;
    for i in (0..numels.len()).rev() {
        let n = numels[i];
        if !current.is_empty() && filled + n > cap {
            buckets.push(std::mem::take(&mut current));
            filled = 0;
        }
        current.push(i);
        filled += n;
    }
    if !current.is_empty() {
        buckets.push(current);
    }
    buckets
}

/// Replaces every gradient in `grads` and every value in `scalars` (the
/// loss terms) by its mean over the ranks of `collective`. Every rank holds
/// `batch_size / world` items, so this is the gradient of the global batch's
/// mean loss.
pub fn average_gradients(
    collective: &mut dyn Collective,
    grads: &[Tensor],
    scalars: &mut [f64],
) -> Result<()> {
    let world = collective.world();
    let numels: Vec<usize> = grads.iter().map(|g| g.numel()).collect();
    let total: usize = numels.iter().sum();
    let mut row = vec![grads.len() as f64, total as f64];
    row.extend_from_slice(scalars);
    let rows = collective.all_gather_f64(&row)?;
    let differs: Vec<String> = rows
        .iter()
        .enumerate()
        .filter(|(_, r)| r.get(..2) != rows[0].get(..2))
        .map(|(rank, r)| {
            format!(
                "rank {rank} holds {} gradients of {} values",
                r.first().copied().unwrap_or(f64::NAN),
                r.get(1).copied().unwrap_or(f64::NAN)
            )
        })
        .collect();
    if !differs.is_empty() {
        return Err(TrainError::input(
            "data-parallel gradients",
            format!(
                "the ranks hold different gradients: rank 0 holds {} gradients of {} values, {} \
                 (different models? every rank must train the same config); rank {} stops",
                rows[0][0],
                rows[0][1],
                differs.join(", "),
                collective.rank()
            ),
        ));
    }
    for (k, v) in scalars.iter_mut().enumerate() {
        *v = rows.iter().map(|r| r[2 + k]).sum::<f64>() / world as f64;
    }
    let buckets = bucket_ranges(&numels, collective.bucket_bytes());
    let scale = 1.0 / world as f64;
    let mut make = |b: usize| -> Result<Tensor> {
        let parts: Vec<Tensor> = buckets[b]
            .iter()
            .map(|&i| grads[i].to_kind(Kind::Float).reshape(-1))
            .collect();
        Ok(tch::no_grad(|| Tensor::cat(&parts, 0) * scale).contiguous()) // [bucket values]
    };
    let mut done = |b: usize, flat: Tensor| -> Result<()> {
        tch::no_grad(|| {
            let mut offset = 0i64;
            for &i in &buckets[b] {
                let g = &grads[i];
                let n = numels[i] as i64;
                let chunk = flat.narrow(0, offset, n).view(g.size().as_slice()); // gradient's shape
                g.shallow_clone().copy_(&chunk.to_kind(g.kind()));
                offset += n;
            }
        });
        Ok(())
    };
    collective.all_reduce_buckets(buckets.len(), &mut make, &mut done)
}
