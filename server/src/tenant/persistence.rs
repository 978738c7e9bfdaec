//! A tenant's objects in its [`Store`]: written with every change (a change whose write fails is undone where it
//! can be, and reported; the file is written before the change and put in place with it, see [`Pending`]), and
//! restored at start: buffers first, then accels, each after the accels it places. An
//! accel saved against an older version of a child (the child was updated since, and the accel not) comes back
//! stale, refusing traces until it is updated, as it did before the restart.

use std::collections::HashMap;
use std::sync::Arc;

use rayd_engine::Accel;

use super::{AccelEntry, BufferEntry, DEFAULT_DEVICE, Tenant};
use crate::error::{ServiceError, ServiceResult};
use crate::persist::{AccelRecord, BufferRecord, ChildRecord, Prepared, Store, id_number};

/// What a restore did.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Restored {
    /// Buffers restored.
    pub buffers: usize,
    /// Accels restored.
    pub accels: usize,
    /// Of those, accels that place an older version of a child and refuse traces until updated.
    pub stale: usize,
    /// Objects skipped: the file (or handle) and why.
    pub skipped: Vec<(String, String)>,
}

/// An object's file written beside its place, to be put there with the change it records: writing takes as long
/// as the object is large, and is done before [`Tenant::keeping`] is taken; the quick put, under it. Dropped
/// without [`Pending::put`], the written file is removed.
#[must_use = "the file is removed unless it is put in place"]
pub(super) struct Pending(Option<(Prepared, String)>);

impl Pending {
    /// The file that `written` wrote (storing `what`), or why it could not be written.
    fn of(what: String, written: std::io::Result<Prepared>) -> ServiceResult<Pending> {
        match written {
            Ok(prepared) => Ok(Pending(Some((prepared, what)))),
            Err(e) => Err(ServiceError::storage(what, e)),
        }
    }

    /// Puts the file in place (nothing without a store).
    pub(super) fn put(self) -> ServiceResult<()> {
        let Some((prepared, what)) = self.0 else { return Ok(()) };
        prepared.put().map_err(|e| ServiceError::storage(what, e))
    }
}

/// Of `objects` in creation order, those that no later one of the same name supersedes; the others are added to
/// `skipped`. Two files of one name are left only when the older was skipped at a start (limits lowered, a device
/// missing) and the name was then given to a new object: the new one, which its client was told of, comes back, not
/// the old one over it. `name_and_id` gives an object's name (empty: none) and id.
fn newest_of_each_name<R>(
    objects: Vec<(R, bytes::Bytes)>,
    name_and_id: impl Fn(&R) -> (&String, &String),
    skipped: &mut Vec<(String, String)>,
) -> Vec<(R, bytes::Bytes)> {
    let mut newest: HashMap<String, String> = HashMap::new();
    for (record, _) in &objects {
        let (name, id) = name_and_id(record);
        if !name.is_empty() {
            newest.insert(name.clone(), id.clone());
        }
    }
    let (kept, superseded): (Vec<_>, Vec<_>) = objects.into_iter().partition(|(record, _)| {
        let (name, id) = name_and_id(record);
        name.is_empty() || newest[name] == *id
    });
    for (record, _) in superseded {
        let (name, id) = name_and_id(&record);
        skipped.push((id.clone(), format!("{} of the same name {name:?} is newer", newest[name])));
    }
    kept
}

impl Tenant {
    /// Persists this tenant's objects in `store` from now on.
    pub fn with_store(self, store: Store) -> Tenant {
        Tenant { store: Some(store), ..self }
    }

    /// Writes `entry`'s accel (its children referred to) to a file of the store, if there is one, to be put in
    /// place. Its children are registered accels or among `arriving` (made with it, registered with it).
    pub(super) fn prepare_accel_file(&self, entry: &AccelEntry, arriving: &[AccelEntry]) -> ServiceResult<Pending> {
        let Some(store) = &self.store else { return Ok(Pending(None)) };
        let children = entry.accel.children();
        let registered = self.accels.values();
        let child_records = children
            .iter()
            .map(|child| {
                let mut known = registered.iter().chain(arriving);
                let placed = known.find(|e| Arc::ptr_eq(&e.accel, child)).ok_or_else(|| {
                    ServiceError::Precondition(format!("accel {:?} places an accel that is not registered", entry.name))
                })?;
                Ok(ChildRecord { handle: placed.handle.clone(), version: placed.version })
            })
            .collect::<ServiceResult<Vec<_>>>()?;
        let blob = self.context(&entry.device)?.1.serialize_accel(&entry.accel, children)?;
        let record = AccelRecord {
            name: entry.name.clone(),
            handle: entry.handle.clone(),
            device: entry.device.clone(),
            build_ns: entry.build_ns,
            version: entry.version,
            children: child_records,
        };
        Pending::of(format!("storing accel {:?}", entry.name), store.prepare_accel(&record, &blob))
    }

    /// Removes an accel from the store, if there is one.
    pub(super) fn unpersist_accel(&self, handle: &str) -> ServiceResult<()> {
        let Some(store) = &self.store else { return Ok(()) };
        store.remove_accel(handle).map_err(|e| ServiceError::storage(format!("removing the file of accel {handle}"), e))
    }

    /// Writes a buffer to a file of the store, if there is one, to be put in place.
    pub(super) fn prepare_buffer_file(&self, entry: &BufferEntry) -> ServiceResult<Pending> {
        let Some(store) = &self.store else { return Ok(Pending(None)) };
        let data = self.context(DEFAULT_DEVICE)?.1.buffer(entry.handle)?;
        let record = BufferRecord { id: entry.id.clone(), name: entry.name.clone() };
        Pending::of(format!("storing buffer {}", entry.id), store.prepare_buffer(&record, &data))
    }

    /// Removes a buffer from the store, if there is one.
    pub(super) fn unpersist_buffer(&self, id: &str) -> ServiceResult<()> {
        let Some(store) = &self.store else { return Ok(()) };
        store.remove_buffer(id).map_err(|e| ServiceError::storage(format!("removing the file of buffer {id}"), e))
    }

    /// Restores every object of the store (nothing without one), under the ids, handles and names it had. Files
    /// that cannot be used are skipped with the reason, and so are accels whose children could not be restored.
    pub fn restore(&self) -> ServiceResult<Restored> {
        let Some(store) = &self.store else { return Ok(Restored::default()) };
        let stored = store.read_all().map_err(|e| ServiceError::storage("reading the stored objects".into(), e))?;
        // New objects must never take an id or handle a stored one has, restored or skipped (a skipped file stays
        // for the operator, and a new object's file must not replace it), nor one a deleted object had (a client
        // may still hold it).
        let skipped =
            stored.skipped.iter().map(|(path, _)| path.file_stem().and_then(|stem| id_number(&stem.to_string_lossy())));
        let highest = stored
            .buffers
            .iter()
            .map(|(r, _)| id_number(&r.id))
            .chain(stored.accels.iter().map(|(r, _)| id_number(&r.handle)))
            .chain(skipped);
        let highest = highest.flatten().chain([store.highest_issued()]).max().unwrap_or(0);
        let mut restored = Restored {
            skipped: stored.skipped.into_iter().map(|(path, why)| (path.display().to_string(), why)).collect(),
            ..Restored::default()
        };
        self.next_buffer.fetch_max(highest.saturating_add(1), std::sync::atomic::Ordering::Relaxed);
        for context in self.contexts.values() {
            context.advance_handles(highest);
        }
        // In creation order (file names sort buf-10 before buf-2), so buffers list as they did before.
        let mut buffers = stored.buffers;
        buffers.sort_by_key(|(record, _)| id_number(&record.id));
        let buffers = newest_of_each_name(buffers, |r| (&r.name, &r.id), &mut restored.skipped);
        for (record, data) in buffers {
            match self.restore_buffer(&record, data) {
                Ok(()) => restored.buffers += 1,
                Err(e) => restored.skipped.push((record.id, e.to_string())),
            }
        }
        let mut pending: Vec<(AccelRecord, bytes::Bytes)> = stored.accels;
        pending.sort_by_key(|(record, _)| id_number(&record.handle));
        let mut pending = newest_of_each_name(pending, |r| (&r.name, &r.handle), &mut restored.skipped);
        let mut by_handle: HashMap<String, AccelEntry> = HashMap::new();
        while !pending.is_empty() {
            let ready = |record: &AccelRecord| record.children.iter().all(|c| by_handle.contains_key(&c.handle));
            let Some(next) = pending.iter().position(|(record, _)| ready(record)) else { break };
            let (record, blob) = pending.remove(next);
            match self.restore_accel(&record, &blob, &by_handle) {
                Ok((entry, stale)) => {
                    restored.accels += 1;
                    restored.stale += usize::from(stale);
                    by_handle.insert(record.handle, entry);
                }
                Err(e) => restored.skipped.push((record.handle, e.to_string())),
            }
        }
        for (record, _) in pending {
            let missing: Vec<&str> = record
                .children
                .iter()
                .map(|c| c.handle.as_str())
                .filter(|handle| !by_handle.contains_key(*handle))
                .collect();
            restored.skipped.push((record.handle, format!("its children {missing:?} could not be restored")));
        }
        Ok(restored)
    }

    /// Restores one buffer under its id and name, within the tenant's buffer limits.
    fn restore_buffer(&self, record: &BufferRecord, data: bytes::Bytes) -> ServiceResult<()> {
        self.check_new_buffers("name", &[(&record.name, data.len() as u64)])?;
        let size_bytes = data.len() as u64;
        let context = self.context(DEFAULT_DEVICE)?.1;
        let handle = context.create_buffer(data);
        let entry = BufferEntry { id: record.id.clone(), name: record.name.clone(), handle, size_bytes };
        self.buffers.insert(record.id.clone(), &record.name, entry).inspect_err(|_| {
            let _ = context.destroy_buffer(handle);
        })
    }

    /// Restores one accel over its restored children, within the tenant's accel limits; also says whether it comes
    /// back stale.
    fn restore_accel(
        &self,
        record: &AccelRecord,
        blob: &[u8],
        restored: &HashMap<String, AccelEntry>,
    ) -> ServiceResult<(AccelEntry, bool)> {
        let children: Vec<Arc<Accel>> =
            record.children.iter().map(|c| Arc::clone(&restored[&c.handle].accel)).collect();
        let stale = record.children.iter().any(|c| restored[&c.handle].version != c.version);
        let (device, context) = self.context(&record.device)?;
        let accel = context
            .deserialize_accel(blob, &children)?
            .pop()
            .ok_or_else(|| ServiceError::Precondition(format!("the file of accel {} holds no accel", record.handle)))?;
        if stale {
            context.mark_stale(&accel);
        }
        let entry = AccelEntry {
            accel,
            name: record.name.clone(),
            handle: record.handle.clone(),
            device: device.into(),
            build_ns: record.build_ns,
            version: record.version,
            pace: Arc::default(),
        };
        // Held to the limits, as a load is: they may have been lowered since the accel was stored.
        let kept = self.reserve_accels(1).and_then(|_counted| {
            let describe = |_| format!("accel {}", record.handle);
            let _bytes = self.check_made(std::slice::from_ref(&entry.accel), 0, describe)?;
            self.accels.insert(record.handle.clone(), &record.name, entry.clone())
        });
        kept.inspect_err(|_| {
            let _ = context.destroy_accel(entry.accel.handle());
        })?;
        crate::metrics::accel_built(&self.name, &entry);
        Ok((entry, stale))
    }
}
