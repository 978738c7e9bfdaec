//! Reading a blob: the header, the external accels given against what the blob recorded of them, then each
//! entry in turn, made into an accel of the context over the accels before it. A failure takes back every accel
//! already made.

use std::sync::Arc;

use super::entry::{EXTERNAL_BIT, Entry, ExternalRecord, kind_of};
use super::header::{HEADER_BYTES, Header};
use super::wire::{Reader, invalid};
use crate::accel::AccelKind;
use crate::context::{Accel, Context};
use crate::error::{Error, Result};
use crate::geometry::MAX_GRAPH_DEPTH;

/// Creates in `context` every accel `blob` embeds, children first, over the `external` accels it refers to.
pub(crate) fn accels(context: &Context, blob: &[u8], external: &[Arc<Accel>]) -> Result<Vec<Arc<Accel>>> {
    let header = Header::read(blob)?;
    let device = context.device().info().kind;
    header.check_backend(device, context.backend().layout_version())?;
    if external.len() != header.external as usize {
        return Err(Error::InvalidExternal(format!(
            "{} given, the blob refers to {}",
            external.len(),
            header.external
        )));
    }
    let mut reader = Reader::new(&blob[HEADER_BYTES..]);
    let records: Vec<ExternalRecord> = reader.array("external accels")?;
    if records.len() != external.len() {
        return Err(invalid(format!("{} external records, the header counts {}", records.len(), external.len())));
    }
    for (index, (accel, record)) in external.iter().zip(&records).enumerate() {
        check_external(index, accel, record, device)?;
    }
    let mut made = Made { context, accels: Vec::new() };
    for index in 0..header.accels as usize {
        let accel = Entry::read(&mut reader, index, external.len())
            .and_then(|entry| make(context, entry, &made.accels, external))
            .map_err(|e| within(index, e))?;
        made.accels.push(accel);
    }
    reader.finish("the payload")?;
    Ok(made.keep())
}

/// Checks external accel `index` against what the blob recorded of it.
fn check_external(
    index: usize,
    accel: &Accel,
    record: &ExternalRecord,
    device: crate::backend::BackendKind,
) -> Result<()> {
    if accel.backend_kind() != device {
        return Err(Error::FailedPrecondition(format!(
            "external accel {index} (accel {}) is a {:?} accel; this context's device is {device:?}",
            accel.handle().0,
            accel.backend_kind()
        )));
    }
    let given = ExternalRecord::of(accel);
    if !given.matches(record) {
        let kind = kind_of(record.kind)?;
        return Err(Error::InvalidExternal(format!(
            "external accel {index} (accel {}) is a {:?} accel with bounds {:?}; the blob was made over a {kind:?} \
             accel with bounds {:?}",
            accel.handle().0,
            accel.info().kind,
            accel.info().bounds,
            record.bounds
        )));
    }
    Ok(())
}

/// Makes the accel of `entry` in `context`, over the accels `made` before it and `external`.
fn make(context: &Context, entry: Entry<'_>, made: &[Arc<Accel>], external: &[Arc<Accel>]) -> Result<Arc<Accel>> {
    let children: Vec<Arc<Accel>> = entry
        .children
        .iter()
        .map(|&code| match code & EXTERNAL_BIT {
            0 => Arc::clone(&made[code as usize]),
            _ => Arc::clone(&external[(code & !EXTERNAL_BIT) as usize]),
        })
        .collect();
    let deepest = children.iter().map(|c| c.info().depth).max().unwrap_or(0);
    if deepest >= MAX_GRAPH_DEPTH {
        return Err(invalid(format!(
            "it would head a graph of {} levels, more than {MAX_GRAPH_DEPTH}",
            u64::from(deepest) + 1
        )));
    }
    let backend = context.backend();
    let data = match (entry.shape.kind, &entry.transform, children.as_slice()) {
        (AccelKind::Triangles | AccelKind::Instances, _, _) => {
            backend.decode(&entry.shape, &entry.options, entry.payload, &children)?
        }
        (_, Some(transform), [child]) if entry.payload.is_empty() => backend.build_transform(transform, child)?,
        _ => return Err(invalid("a transform with a backend payload")),
    };
    Ok(context.register(entry.shape, &entry.options, data, children, entry.retained))
}

/// `error`, when it is about the blob, said to be about accel `index`.
fn within(index: usize, error: Error) -> Error {
    match error {
        Error::InvalidBlob(what) => Error::InvalidBlob(format!("accel {index}: {what}")),
        other => other,
    }
}

/// The accels made so far from a blob: destroyed again, last first, unless kept.
struct Made<'a> {
    /// Their context.
    context: &'a Context,
    /// The accels, in the blob's order.
    accels: Vec<Arc<Accel>>,
}

impl Made<'_> {
    /// Keeps the accels made.
    fn keep(mut self) -> Vec<Arc<Accel>> {
        std::mem::take(&mut self.accels)
    }
}

impl Drop for Made<'_> {
    fn drop(&mut self) {
        while let Some(accel) = self.accels.pop() {
            // Nothing but accels made after it places it, and those are gone: it can be destroyed.
            let _ = self.context.destroy_accel(accel.handle());
        }
    }
}
