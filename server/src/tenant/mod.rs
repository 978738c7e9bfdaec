//! A tenant's objects and the operations on them, in engine terms: named accels on any device, buffers, and
//! traces. Every operation checks the configured limits before it allocates. With a data directory every change
//! is also persisted, and restored at start ([`persistence`]).

mod caller;
mod persistence;
mod quota;
mod trace;

pub use caller::Caller;
use quota::Reservation;
pub use trace::Rays;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Instant;

use bytes::Bytes;
use rayd_engine::accel::MemoryUsage;
use rayd_engine::query::TraceStats;
use rayd_engine::{Accel, BufferHandle, Context, Device};

use crate::config::Limits;
use crate::error::{ServiceError, ServiceResult, quoted};
use crate::persist::Store;
use crate::registry::Registry;
use crate::schedule::{Flow, Pace, Schedulers};
use crate::streams::Streams;
use quota::Quotas;

/// The device used when a request names none.
pub const DEFAULT_DEVICE: &str = "cpu:0";

/// A built accel under its tenant's name.
#[derive(Debug, Clone)]
pub struct AccelEntry {
    /// The engine's accel (shared with traces running on it).
    pub accel: Arc<Accel>,
    /// The tenant's name for it.
    pub name: String,
    /// Its opaque handle in the contract.
    pub handle: String,
    /// The device it lives on.
    pub device: String,
    /// How long the build took.
    pub build_ns: u64,
    /// Updates so far.
    pub version: u64,
    /// How fast its rays were traced lately, which sizes the first piece of its next trace (shared by its versions).
    pub pace: Arc<Pace>,
}

/// A buffer under its id.
#[derive(Debug, Clone)]
pub struct BufferEntry {
    /// `buf-N`.
    pub id: String,
    /// The caller's name, or empty.
    pub name: String,
    /// Its handle in the CPU context, which holds and accounts its bytes.
    handle: BufferHandle,
    /// Its size.
    pub size_bytes: u64,
}

/// The results of one trace, ready to be put in a reply without copying.
#[derive(Debug, Default)]
pub struct TraceResult {
    /// Hit records (empty for a reduced trace).
    pub hits: Bytes,
    /// Counts (`all` and `count` queries), else empty.
    pub counts: Bytes,
    /// The reduction's result, for a reduced trace.
    pub reduced: Option<rayd_engine::reduce::Reduced>,
    /// What the engine did.
    pub stats: TraceStats,
    /// Time spent in the engine.
    pub trace_ns: u64,
    /// Pieces the trace was cut into ([`crate::schedule::PieceSizer`]).
    pub pieces: usize,
}

/// Everything one tenant has built, and the limits it is held to.
#[derive(Debug)]
pub struct Tenant {
    /// Its name (`default` without configured tenants).
    name: String,
    /// The limits of every request.
    limits: Limits,
    /// One context per device, by device id.
    contexts: HashMap<String, Context>,
    /// Accels by handle and name.
    accels: Registry<AccelEntry>,
    /// Buffers by id and name.
    buffers: Registry<BufferEntry>,
    /// The next buffer number.
    next_buffer: AtomicU64,
    /// Open streams.
    streams: Arc<Streams>,
    /// Where objects are persisted, with a data directory.
    store: Option<Store>,
    /// Operations running and rays allowed.
    quotas: Quotas,
    /// Held while an object and its file change together (made and put in place, removed and unwritten, replaced
    /// and rewritten), so that an object removed while it is being made never leaves its file behind to come back
    /// at the next start. Files are written before it is taken, and only renamed into place under it
    /// ([`persistence::Pending`]): a large object's write never holds up the tenant's other changes.
    keeping: Mutex<()>,
    /// Versions of its accels that an update replaced or a destroy removed, while something may still hold them
    /// (an instance accel placing one, a trace or a stream): their bytes count against `max_total_accel_bytes`
    /// until they are gone ([`Tenant::accel_bytes`]).
    departed: Mutex<Vec<Weak<Accel>>>,
    /// Its queue in the devices' schedulers, and its share of them.
    flow: Flow,
    /// The fair schedulers of the server's devices, shared with every tenant.
    schedulers: Arc<Schedulers>,
}

/// What a tenant holds now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Usage {
    /// Accels.
    pub accels: u32,
    /// Buffers.
    pub buffers: u32,
    /// Bytes of accels and buffers on every device, as the contexts account them.
    pub object_bytes: u64,
    /// Streams open.
    pub streams: u32,
    /// Bytes the streams hold.
    pub stream_bytes: u64,
    /// Bytes of its accels.
    pub accel_bytes: u64,
    /// Bytes of its buffers.
    pub buffer_bytes: u64,
    /// Operations running now.
    pub operations: u32,
}

/// A new buffer's bytes and its place among the tenant's buffers, reserved while it is made.
#[derive(Debug)]
pub struct BufferReservation {
    /// Its bytes, against `max_total_buffer_bytes`.
    bytes: Reservation,
    /// Its place, against `max_buffers`.
    count: Reservation,
}

/// The longest accel or buffer name, in characters.
pub const MAX_NAME_CHARS: usize = 128;

/// Checks an accel or buffer name: 1 to [`MAX_NAME_CHARS`] characters of `[A-Za-z0-9._-]`.
pub fn check_name(field: &str, name: &str) -> ServiceResult<()> {
    let valid = (1..=MAX_NAME_CHARS).contains(&name.len())
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b));
    if !valid {
        let rule = format!("{} must be 1 to {MAX_NAME_CHARS} characters of [A-Za-z0-9._-]", quoted(name));
        return Err(ServiceError::invalid(field, rule));
    }
    Ok(())
}

/// A context on each device, by device id, sharing one sequence of handles (accel ids are their handles, so two
/// devices' accels must never get the same one).
fn contexts(devices: &[Device]) -> HashMap<String, Context> {
    let Some((first, rest)) = devices.split_first() else { return HashMap::new() };
    let first_context = Context::new(first.clone());
    let mut contexts: HashMap<String, Context> = rest
        .iter()
        .map(|device| (device.info().id.clone(), Context::sharing_handles(device.clone(), &first_context)))
        .collect();
    contexts.insert(first.info().id.clone(), first_context);
    contexts
}

impl Tenant {
    /// A tenant called `name` with a context on each device, whose traces get `share` of the devices' `schedulers`.
    pub fn new(name: &str, limits: Limits, share: u32, devices: &[Device], schedulers: Arc<Schedulers>) -> Tenant {
        Tenant {
            name: name.into(),
            limits,
            contexts: contexts(devices),
            accels: Registry::new("accel"),
            buffers: Registry::new("buffer"),
            next_buffer: AtomicU64::new(1),
            streams: Arc::default(),
            store: None,
            quotas: Quotas::new(limits.max_rays_per_second),
            keeping: Mutex::new(()),
            departed: Mutex::default(),
            flow: Flow { name: name.into(), share },
            schedulers,
        }
    }

    /// The tenant's streams.
    pub fn streams(&self) -> &Arc<Streams> {
        &self.streams
    }

    /// Its name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Its weight in the devices' fair schedulers.
    pub fn share(&self) -> u32 {
        self.flow.share
    }

    /// Bytes of the tenant's accels.
    fn accel_bytes(&self) -> u64 {
        let held: u64 = self.accels.values().iter().map(|e| e.accel.info().size_bytes).sum();
        let mut departed = self.departed.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        departed.retain(|version| version.strong_count() > 0);
        held + departed.iter().filter_map(Weak::upgrade).map(|accel| accel.info().size_bytes).sum::<u64>()
    }

    /// Counts `version` (an accel that an update replaced or a destroy removed) among the tenant's accel bytes for
    /// as long as something still holds it.
    fn depart(&self, version: &Arc<Accel>) {
        let mut departed = self.departed.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        // Versions nothing holds any more are dropped here too, so that a tenant that only updates (a refit each
        // frame) does not pile up their entries between the counts that prune them.
        departed.retain(|version| version.strong_count() > 0);
        departed.push(Arc::downgrade(version));
    }

    /// Bytes of the tenant's buffers.
    fn buffer_bytes(&self) -> u64 {
        self.buffers.values().iter().map(|b| b.size_bytes).sum()
    }

    /// What the tenant holds now.
    pub fn usage(&self) -> Usage {
        Usage {
            accels: self.accels.len() as u32,
            buffers: self.buffers.len() as u32,
            object_bytes: self.contexts.values().map(Context::memory_in_use).sum(),
            streams: self.streams.open_count(),
            stream_bytes: self.streams.held_bytes(),
            accel_bytes: self.accel_bytes(),
            buffer_bytes: self.buffer_bytes(),
            operations: self.quotas.running(),
        }
    }

    /// The limits of this tenant's requests.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// The context on device `id` (empty: the default device), and the device's id.
    pub fn context(&self, id: &str) -> ServiceResult<(&str, &Context)> {
        let id = if id.is_empty() { DEFAULT_DEVICE } else { id };
        self.contexts.get_key_value(id).map(|(k, c)| (k.as_str(), c)).ok_or_else(|| ServiceError::NotFound {
            what: "device",
            name: id.into(),
            field: String::new(),
        })
    }

    /// Builds an accel named `name` on `device` with `build` for `caller`, after checking the name, the accel count
    /// and the output bound `usage` gives against the limits; the accel and those bytes stay reserved until it is
    /// kept, so that builds at once cannot together outgrow them. Neither started nor kept once `caller` has gone.
    /// Blocks: call it off the async runtime.
    pub fn build_accel(
        &self,
        name: &str,
        device: &str,
        caller: &Caller,
        usage: impl FnOnce(&Context) -> rayd_engine::Result<MemoryUsage>,
        build: impl FnOnce(&Context) -> rayd_engine::Result<Arc<Accel>>,
    ) -> ServiceResult<AccelEntry> {
        check_name("name", name)?;
        self.accels.check_free(name)?;
        let _running = self.quotas.start(self.limits.max_concurrent_operations)?;
        let _counted = self.reserve_accels(1)?;
        let (device, context) = self.context(device)?;
        let usage = usage(context)?;
        ServiceError::check_limit(
            || format!("accel {name:?} needs up to {} bytes", usage.output_bytes),
            usage.output_bytes,
            "max_accel_bytes",
            self.limits.max_accel_bytes,
        )?;
        let bound = self.reserve_accel_bytes(usage.output_bytes)?;
        let what = || format!("accel {name:?} was not kept");
        caller.check(what)?;
        let start = Instant::now();
        let accel = build(context).map_err(|failed| match caller.check(what) {
            // A build stopped because its caller went, or one that failed for a caller who is no longer there.
            Err(gone) => gone,
            Ok(()) => failed.into(),
        })?;
        let describe = |_| format!("accel {name:?}, built");
        // A caller gone by now is not worth the accel's file.
        let checked = caller
            .check(what)
            .and_then(|()| self.check_made(std::slice::from_ref(&accel), usage.output_bytes, describe));
        let _reserved = match checked {
            Ok(beyond_the_bound) => (bound, beyond_the_bound),
            Err(refused) => {
                context.destroy_accel(accel.handle())?;
                return Err(refused);
            }
        };
        let entry = AccelEntry {
            handle: format!("acc-{}", accel.handle().0),
            accel,
            name: name.into(),
            device: device.into(),
            build_ns: start.elapsed().as_nanos() as u64,
            version: 0,
            pace: Arc::default(),
        };
        let file = match self.prepare_accel_file(&entry, &[]) {
            Ok(file) => file,
            Err(unsaved) => {
                context.destroy_accel(entry.accel.handle())?;
                return Err(unsaved);
            }
        };
        let _keeping = self.keep();
        // Its file goes in place before it is listed, so that no other call can place an accel whose file may yet
        // fail. The name is checked first: nothing is listed in between, every insert holding the keeping lock.
        if let Err(refused) = caller.check(what).and_then(|()| self.accels.check_free(name)).and_then(|()| file.put()) {
            // A put can fail after its rename (syncing the directory): the file goes too. The error is the refusal.
            let _ = self.unpersist_accel(&entry.handle);
            context.destroy_accel(entry.accel.handle())?;
            return Err(refused);
        }
        self.accels.insert(entry.handle.clone(), name, entry.clone())?;
        crate::metrics::accel_built(&self.name, &entry);
        Ok(entry)
    }

    /// Recreates the accels of a saved blob on `device`: the root called `name`, the accels below it `name.1`,
    /// `name.2`, … in the blob's order, after checking the names, the blob's size against `max_accel_bytes` and
    /// `max_total_accel_bytes` and the accel count against `max_accels` (reserved until they are kept); once loaded,
    /// each accel's own bytes against `max_accel_bytes` and their sum against `max_total_accel_bytes` (a loaded
    /// accel can take more bytes than its part of the blob). All or nothing: nothing once `caller` has gone. Blocks:
    /// call it off the async runtime.
    pub fn load_accels(
        &self,
        name: &str,
        device: &str,
        caller: &Caller,
        blob: &[u8],
    ) -> ServiceResult<Vec<AccelEntry>> {
        check_name("name", name)?;
        ServiceError::check_limit(
            || "the blob's bytes".into(),
            blob.len() as u64,
            "max_accel_bytes",
            self.limits.max_accel_bytes,
        )?;
        let summary = rayd_engine::serialize::blob_summary(blob)?;
        let _running = self.quotas.start(self.limits.max_concurrent_operations)?;
        let _counted = self.reserve_accels(u64::from(summary.accels))?;
        let blob_bytes = self.reserve_accel_bytes(blob.len() as u64)?;
        let names: Vec<String> = (1..summary.accels).map(|i| format!("{name}.{i}")).chain([name.to_owned()]).collect();
        for name in &names {
            check_name("name", name)?;
            self.accels.check_free(name)?;
        }
        let (device, context) = self.context(device)?;
        let what = || format!("the accels of the blob loaded as {name:?} were not kept");
        caller.check(what)?;
        let start = Instant::now();
        let accels = context.deserialize_accel(blob, &[])?;
        let build_ns = start.elapsed().as_nanos() as u64;
        let describe = |index| format!("accel {index} of the blob, loaded");
        let kept = caller.check(what).and_then(|()| self.check_made(&accels, blob.len() as u64, describe)).and_then(
            |loaded_bytes| {
                let _reserved = (blob_bytes, loaded_bytes);
                self.keep_loaded(&accels, names, device, build_ns, caller, what)
            },
        );
        kept.or_else(|refused| {
            destroy_made(context, accels)?;
            Err(refused)
        })
    }

    /// Keeps the accels a load made under `names`, with their files: all, or none (the error, each file put taken
    /// back, none listed, and no clone of an accel left, so that the caller can destroy them).
    fn keep_loaded(
        &self,
        accels: &[Arc<Accel>],
        names: Vec<String>,
        device: &str,
        build_ns: u64,
        caller: &Caller,
        what: impl FnOnce() -> String,
    ) -> ServiceResult<Vec<AccelEntry>> {
        let loaded = accels.iter().zip(names).map(|(accel, name)| AccelEntry {
            handle: format!("acc-{}", accel.handle().0),
            accel: Arc::clone(accel),
            name,
            device: device.into(),
            build_ns,
            version: 0,
            pace: Arc::default(),
        });
        let loaded: Vec<AccelEntry> = loaded.collect();
        let files =
            loaded.iter().map(|entry| self.prepare_accel_file(entry, &loaded)).collect::<ServiceResult<Vec<_>>>()?;
        let _keeping = self.keep();
        caller.check(what)?;
        loaded.iter().try_for_each(|entry| self.accels.check_free(&entry.name))?;
        // Files in place before any accel is listed, as a build's (`build_accel`); a file that fails takes back
        // those put before it (all of them, even past one that cannot be: the first such error is the answer).
        for (put, file) in files.into_iter().enumerate() {
            if let Err(unsaved) = file.put() {
                // The one that failed too: it can fail after its rename.
                loaded[..=put].iter().map(|entry| self.unpersist_accel(&entry.handle)).fold(Ok(()), Result::and)?;
                return Err(unsaved);
            }
        }
        for entry in &loaded {
            self.accels.insert(entry.handle.clone(), &entry.name, entry.clone())?;
            crate::metrics::accel_built(&self.name, entry);
        }
        Ok(loaded)
    }

    /// Updates `entry`'s accel with `update` (which gets its context) and keeps the new version under the same handle
    /// and name; not started once `caller` has gone (an update that has started replaces the version as it ends).
    /// An update that cannot be stored is undone.
    /// Blocks: call it off the async runtime.
    pub fn update_accel(
        &self,
        entry: &AccelEntry,
        caller: &Caller,
        update: impl FnOnce(&Context) -> rayd_engine::Result<Arc<Accel>>,
    ) -> ServiceResult<AccelEntry> {
        let (_, context) = self.context(&entry.device)?;
        let _running = self.quotas.start(self.limits.max_concurrent_operations)?;
        caller.check(|| format!("the update of accel {:?} was not started", entry.name))?;
        let start = Instant::now();
        let accel = update(context)?;
        let build_ns = start.elapsed().as_nanos() as u64;
        let updated = AccelEntry { accel, build_ns, version: entry.version + 1, ..entry.clone() };
        let reserved = self.reserve_updated_bytes(entry, &updated);
        let file = reserved.and_then(|reserved| Ok((reserved, self.prepare_accel_file(&updated, &[])?)));
        let _keeping = self.keep();
        // Stored, then listed: until then no call can find the new version to update it again, so that an update
        // that cannot be kept can be undone (it changes nothing: the old version is current again).
        let stored = file.and_then(|(reserved, file)| {
            self.accels.get(Some(&entry.handle), None)?;
            file.put()?;
            Ok(reserved)
        });
        // Reserved until listed, where the new version's bytes are counted.
        let _reserved = match stored {
            Ok(reserved) => reserved,
            Err(unkept) => {
                context.undo_update(&entry.accel, &updated.accel)?;
                return Err(unkept);
            }
        };
        self.accels.replace(&entry.handle, updated.clone())?;
        self.depart(&entry.accel);
        crate::metrics::accel_updated(&self.name, entry, &updated);
        Ok(updated)
    }

    /// The accel with this name or handle.
    pub fn accel(&self, by_name: Option<&str>, by_handle: Option<&str>) -> ServiceResult<AccelEntry> {
        self.accels.get(by_handle, by_name)
    }

    /// Checks that `more` bytes of accels stay within `max_total_accel_bytes` with the tenant's accels.
    /// Reserves `count` more accels against `max_accels` until the reservation is dropped.
    fn reserve_accels(&self, count: u64) -> ServiceResult<Reservation> {
        self.quotas.accels_coming.reserve(
            count,
            || self.accels.len() as u64,
            ("max_accels", self.limits.max_accels as u64),
            |held, coming| format!("accels of this tenant ({held} held, {coming} being made, {count} more)"),
        )
    }

    /// Reserves `bytes` more accel bytes against `max_total_accel_bytes` until the reservation is dropped.
    fn reserve_accel_bytes(&self, bytes: u64) -> ServiceResult<Reservation> {
        self.quotas.accel_bytes_coming.reserve(
            bytes,
            || self.accel_bytes(),
            ("max_total_accel_bytes", self.limits.max_total_accel_bytes),
            |held, coming| format!("accel bytes of this tenant ({held} held, {coming} being made, up to {bytes} more)"),
        )
    }

    /// Checks `updated`, the new version of `entry`'s accel, against `max_accel_bytes`, and reserves what it adds to
    /// the tenant's accel bytes as it takes the old version's place against `max_total_accel_bytes`. Versions that
    /// updates replaced count for as long as something still holds them (a trace running on one), so updates while
    /// traces hold the old versions are refused once those pass the quota: the tenant's accels exceed it by at most
    /// the versions that the updates running at once replace while they are still held.
    fn reserve_updated_bytes(&self, entry: &AccelEntry, updated: &AccelEntry) -> ServiceResult<Reservation> {
        let (old, new) = (entry.accel.info().size_bytes, updated.accel.info().size_bytes);
        let what = || format!("the update of accel {:?}", entry.name);
        ServiceError::check_limit(what, new, "max_accel_bytes", self.limits.max_accel_bytes)?;
        self.reserve_accel_bytes(new.saturating_sub(old))
    }

    /// Checks accels just made (built, or loaded from a blob), for which `reserved` bytes were reserved beforehand,
    /// against the limits: each one's bytes against `max_accel_bytes`, its levels against `max_graph_depth` and its
    /// motion keys against `max_motion_keys` (a build checked those two before; a blob can hold any), `describe`
    /// naming the one by its index; and what their sum exceeds `reserved` by against `max_total_accel_bytes`, which
    /// stays reserved until they are kept. (A blob's accels take more than its bytes.)
    fn check_made(
        &self,
        accels: &[Arc<Accel>],
        reserved: u64,
        describe: impl Fn(usize) -> String,
    ) -> ServiceResult<Option<Reservation>> {
        let mut made = 0u64;
        for (index, accel) in accels.iter().enumerate() {
            let info = accel.info();
            let limits = &self.limits;
            ServiceError::check_limit(|| describe(index), info.size_bytes, "max_accel_bytes", limits.max_accel_bytes)?;
            let levels = || format!("levels of {}", describe(index));
            let (depth, most_depth) = (u64::from(info.depth), u64::from(limits.max_graph_depth));
            ServiceError::check_limit(levels, depth, "max_graph_depth", most_depth)?;
            let keys = || format!("motion keys of {}", describe(index));
            let (motion_keys, most_keys) = (u64::from(info.options.motion.keys), u64::from(limits.max_motion_keys));
            ServiceError::check_limit(keys, motion_keys, "max_motion_keys", most_keys)?;
            made = made.saturating_add(info.size_bytes);
        }
        (made > reserved).then(|| self.reserve_accel_bytes(made - reserved)).transpose()
    }

    /// Every accel, in creation order.
    pub fn accels(&self) -> Vec<AccelEntry> {
        let mut all = self.accels.values();
        all.sort_by_key(|e| e.accel.handle());
        all
    }

    /// Destroys an accel; traces holding it finish first. One that instance accels or transforms place is
    /// refused (FAILED_PRECONDITION) and stays. Its file goes first: when the data directory cannot be written
    /// the accel stays, in memory and on disk, and the error says why.
    pub fn destroy_accel(&self, entry: &AccelEntry) -> ServiceResult<()> {
        let context = self.context(&entry.device)?.1;
        context.check_destroyable(entry.accel.handle())?;
        let _keeping = self.keep();
        // Another call may have destroyed or updated it since `entry` was looked up: NOT_FOUND for the first (its
        // file must not be written back below), the version now listed for the second.
        let entry = &self.accels.get(Some(&entry.handle), None)?;
        // Its file goes once nothing can come to place it, and before it leaves the context: an instance accel that
        // came to place it since the check refuses the destroy with the file still there, and a file that cannot be
        // removed keeps the accel.
        context.destroy_accel_after(entry.accel.handle(), || self.unpersist_accel(&entry.handle))?;
        self.accels.remove(&entry.handle, &entry.name)?;
        self.depart(&entry.accel);
        crate::metrics::accel_destroyed(&self.name, entry);
        Ok(())
    }

    /// Holds [`Tenant::keeping`] while the guard lives.
    fn keep(&self) -> std::sync::MutexGuard<'_, ()> {
        self.keeping.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Checks that the buffers `new` (each a name, which request field `field` gave, and a size) may be created
    /// together: their names, each size against `max_buffer_bytes`, their bytes with those held or being made
    /// against `max_total_buffer_bytes`, their count with those held or being made against `max_buffers`. An empty
    /// name is checked for its size.
    pub fn check_new_buffers(&self, field: &str, new: &[(&str, u64)]) -> ServiceResult<()> {
        self.check_new_buffers_beside(field, new, None)
    }

    /// [`Tenant::check_new_buffers`] of buffers whose own reservation (if any) is `own`: what it reserves is not
    /// counted twice.
    fn check_new_buffers_beside(
        &self,
        field: &str,
        new: &[(&str, u64)],
        own: Option<&BufferReservation>,
    ) -> ServiceResult<()> {
        for &(name, size) in new {
            if !name.is_empty() {
                check_name(field, name)?;
                self.buffers.check_free(name)?;
            }
            let what = || match name {
                "" => format!("the size of the buffer that {field} is for"),
                name => format!("the size of buffer {} ({field})", quoted(name)),
            };
            ServiceError::check_limit(what, size, "max_buffer_bytes", self.limits.max_buffer_bytes)?;
        }
        // What is held is read before what is being made: a buffer kept in between (added to those held, then its
        // reservation let go) is then counted at most once. Outside the lock (`keep`) it may be missed, and the check
        // under the lock, which every buffer passes before it is kept, counts it.
        let (own_bytes, own_count) = own.map_or((0, 0), |own| (own.bytes.amount(), own.count.amount()));
        let size = new.iter().map(|&(_, size)| size).fold(0, u64::saturating_add);
        let held_bytes = self.buffer_bytes();
        let held = held_bytes + self.quotas.buffer_bytes_coming.get().saturating_sub(own_bytes);
        ServiceError::check_limit(
            || format!("buffer bytes of this tenant ({held} held or being made, {size} more)"),
            held.saturating_add(size),
            "max_total_buffer_bytes",
            self.limits.max_total_buffer_bytes,
        )?;
        let held_count = self.buffers.len() as u64;
        let coming = self.quotas.buffers_coming.get().saturating_sub(own_count);
        ServiceError::check_limit(
            || "buffers of this tenant (held or being made)".into(),
            held_count + coming + new.len() as u64,
            "max_buffers",
            self.limits.max_buffers as u64,
        )
    }

    /// Checks new buffers as [`Tenant::check_new_buffers`] does (`field` naming them), and reserves each one's bytes
    /// and place against `max_total_buffer_bytes` and `max_buffers` while they are made (uploaded, or written by a
    /// trace): each reservation is handed to [`Tenant::create_buffer`], which lets it go once the buffer is kept.
    pub fn reserve_new_buffers(&self, field: &str, new: &[(&str, u64)]) -> ServiceResult<Vec<BufferReservation>> {
        self.check_new_buffers(field, new)?;
        let (bytes_limit, count_limit) = (self.limits.max_total_buffer_bytes, u64::from(self.limits.max_buffers));
        new.iter()
            .map(|&(_, size)| {
                let bytes = self.quotas.buffer_bytes_coming.reserve(
                    size,
                    || self.buffer_bytes(),
                    ("max_total_buffer_bytes", bytes_limit),
                    |held, coming| {
                        format!("buffer bytes of this tenant ({held} held, {coming} being made, {size} more)")
                    },
                )?;
                let count = self.quotas.buffers_coming.reserve(
                    1,
                    || self.buffers.len() as u64,
                    ("max_buffers", count_limit),
                    |held, coming| format!("buffers of this tenant ({held} held, {coming} being made, 1 more)"),
                )?;
                Ok(BufferReservation { bytes, count })
            })
            .collect()
    }

    /// Serializes `entry`'s accel (with every accel below it) into a new buffer named `name`, which request field
    /// `field` gave; one of the tenant's operations while it runs (so that at most `max_concurrent_operations` blobs
    /// are being made at once), not kept if `caller` goes first. The name and the count of buffers are checked
    /// before the blob is made; once it is, its bytes and place are reserved as an upload's are, until it is kept.
    /// Blocks: call it off the async runtime.
    pub fn save_accel(
        &self,
        entry: &AccelEntry,
        field: &str,
        name: &str,
        caller: &Caller,
    ) -> ServiceResult<BufferEntry> {
        self.check_new_buffers(field, &[(name, 0)])?;
        let _running = self.quotas.start(self.limits.max_concurrent_operations)?;
        let not_kept = || format!("the blob of accel {:?} was not kept", entry.name);
        caller.check(not_kept)?;
        let blob = self.context(&entry.device)?.1.serialize_accel(&entry.accel, &[])?;
        caller.check(not_kept)?;
        let reserved = self.reserve_new_buffers(field, &[(name, blob.len() as u64)])?;
        let reserved = reserved.into_iter().next().expect("one reservation a buffer");
        self.create_buffer(field, name, Bytes::from(blob), reserved)
    }

    /// Keeps `data` as a buffer named `name`, which request field `field` gave; `reserved` is what was reserved for
    /// it while it was made ([`Tenant::reserve_new_buffers`]), let go once it is kept (or refused). Every buffer is
    /// reserved before it is kept, so that what another call reserves meanwhile counts it.
    pub fn create_buffer(
        &self,
        field: &str,
        name: &str,
        data: Bytes,
        reserved: BufferReservation,
    ) -> ServiceResult<BufferEntry> {
        self.check_new_buffers_beside(field, &[(name, data.len() as u64)], Some(&reserved))?;
        let id = format!("buf-{}", self.next_buffer.fetch_add(1, Ordering::Relaxed));
        let size_bytes = data.len() as u64;
        let context = self.context(DEFAULT_DEVICE)?.1;
        let handle = context.create_buffer(data);
        let entry = BufferEntry { id: id.clone(), name: name.into(), handle, size_bytes };
        let file = match self.prepare_buffer_file(&entry) {
            Ok(file) => file,
            Err(unsaved) => {
                context.destroy_buffer(handle)?;
                return Err(unsaved);
            }
        };
        let _keeping = self.keep();
        // Checked again where changes are ordered: two creates of one name that both passed the check above while
        // their files were written must not both be kept (their bytes and places are reserved already). Its file goes
        // in place before it is listed, as an accel's (`build_accel`).
        let kept =
            self.check_new_buffers_beside(field, &[(name, size_bytes)], Some(&reserved)).and_then(|()| file.put());
        if let Err(refused) = kept {
            // As in `build_accel`: a file renamed into place before the put failed goes too.
            let _ = self.unpersist_buffer(&entry.id);
            context.destroy_buffer(handle)?;
            return Err(refused);
        }
        self.buffers.insert(id, name, entry.clone())?;
        // Counted now among the buffers held: its reservation goes, while changes are still ordered.
        drop(reserved);
        Ok(entry)
    }

    /// The buffer with this id or name.
    pub fn buffer(&self, by_id: Option<&str>, by_name: Option<&str>) -> ServiceResult<(BufferEntry, Bytes)> {
        let entry = self.buffers.get(by_id, by_name)?;
        let bytes = self.context(DEFAULT_DEVICE)?.1.buffer(entry.handle)?;
        Ok((entry, bytes))
    }

    /// Every buffer, in creation order.
    pub fn buffers(&self) -> Vec<BufferEntry> {
        let mut all = self.buffers.values();
        all.sort_by_key(|e| e.handle);
        all
    }

    /// Deletes a buffer. Its file goes first: when the data directory cannot be written the buffer stays.
    pub fn delete_buffer(&self, entry: &BufferEntry) -> ServiceResult<()> {
        let _keeping = self.keep();
        self.unpersist_buffer(&entry.id)?;
        self.buffers.remove(&entry.id, &entry.name)?;
        self.context(DEFAULT_DEVICE)?.1.destroy_buffer(entry.handle)?;
        Ok(())
    }
}

/// Destroys accels a load made that are not kept, the root first: each is dropped before the accels it places are
/// destroyed, which are then placed no more.
fn destroy_made(context: &Context, mut accels: Vec<Arc<Accel>>) -> ServiceResult<()> {
    while let Some(accel) = accels.pop() {
        context.destroy_accel(accel.handle())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicUsize;

    use rayd_engine::accel::{BuildFlags, BuildOptions};
    use rayd_engine::geometry::{BuildInput, TriangleInput};

    use super::*;
    use crate::config::SchedulerConfig;

    /// A tenant on the CPU with `limits`.
    fn cpu_tenant(limits: Limits) -> Tenant {
        let devices = [Device::cpu()];
        let schedulers = Arc::new(Schedulers::new(&devices, &SchedulerConfig::default()));
        Tenant::new("t", limits, 1, &devices, schedulers)
    }

    /// Reserves a buffer of `bytes` bytes named `name`, then keeps it, as an upload does.
    fn create(tenant: &Tenant, name: &str, bytes: Vec<u8>) -> ServiceResult<BufferEntry> {
        let field = "header.name";
        let reserved = tenant.reserve_new_buffers(field, &[(name, bytes.len() as u64)])?.pop().unwrap();
        tenant.create_buffer(field, name, Bytes::from(bytes), reserved)
    }

    #[test]
    fn a_buffer_deleted_while_it_is_being_made_leaves_no_file() {
        let dir = std::env::temp_dir().join(format!("rayd-keeping-{}", std::process::id()));
        let store = || crate::persist::Store::open(&dir, "t").unwrap();
        let tenant = cpu_tenant(Limits::default()).with_store(store());
        let files = || std::fs::read_dir(dir.join("tenants/t/buffers")).unwrap().count();
        // Each round a buffer is made while another thread deletes it as soon as it can be found: it is written
        // while it is still being made, and the delete removes it at once or waits for the file to be written.
        for round in 0..20 {
            let name = format!("victim-{round}");
            std::thread::scope(|scope| {
                let deleter = scope.spawn(|| {
                    loop {
                        if let Ok(entry) = tenant.buffers.get(None, Some(&name)) {
                            break tenant.delete_buffer(&entry);
                        }
                        std::thread::yield_now();
                    }
                });
                let made = create(&tenant, &name, vec![round as u8; 4 << 20]);
                assert!(made.is_ok() && deleter.join().unwrap().is_ok(), "round {round}: made {made:?}");
            });
            assert_eq!((tenant.buffers().len(), files()), (0, 0), "round {round}: a file left behind");
        }
        assert_eq!(cpu_tenant(Limits::default()).with_store(store()).restore().unwrap().buffers, 0);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn files_are_written_before_the_lock_that_orders_changes_is_taken() {
        let dir = std::env::temp_dir().join(format!("rayd-written-first-{}", std::process::id()));
        let tenant = cpu_tenant(Limits::default()).with_store(crate::persist::Store::open(&dir, "t").unwrap());
        let buffers = dir.join("tenants/t/buffers");
        let size = 8 << 20;
        // While another change holds the lock, a create writes its whole file under a temporary name, and puts it
        // in place once the lock is free.
        std::thread::scope(|scope| {
            let held = tenant.keep();
            let create = scope.spawn(|| create(&tenant, "big", vec![1; size]));
            let written_under = |extension: &str| {
                std::fs::read_dir(&buffers).unwrap().map(|entry| entry.unwrap().path()).any(|path| {
                    path.extension().is_some_and(|e| e == extension)
                        && std::fs::metadata(&path).is_ok_and(|m| m.len() > size as u64)
                })
            };
            let waiting_since = Instant::now();
            while !written_under("tmp") {
                assert!(waiting_since.elapsed().as_secs() < 60, "no whole temporary file while the lock is held");
                std::thread::yield_now();
            }
            assert!(!written_under("buf"), "the file is in place before the change holds the lock");
            drop(held);
            create.join().unwrap().unwrap();
            assert!(written_under("buf") && !written_under("tmp"));
        });
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn creates_of_one_name_at_once_keep_one() {
        let dir = tempfile::tempdir().unwrap();
        let store = crate::persist::Store::open(dir.path(), "t").unwrap();
        let tenant = cpu_tenant(Limits::default()).with_store(store);
        let buffers = dir.path().join("tenants/t/buffers");
        let temporary_files = || {
            std::fs::read_dir(&buffers)
                .map_or(0, |d| d.flatten().filter(|e| e.path().extension().is_some_and(|x| x == "tmp")).count())
        };
        // Both find the name free before their files are written, then wait for the lock that orders changes.
        let made: Vec<ServiceResult<BufferEntry>> = std::thread::scope(|scope| {
            let held = tenant.keep();
            let creates: Vec<_> = (0..2).map(|_| scope.spawn(|| create(&tenant, "one", vec![1; 1 << 20]))).collect();
            let waiting_since = Instant::now();
            while temporary_files() < 2 {
                assert!(waiting_since.elapsed().as_secs() < 60, "the two files were never written");
                std::thread::yield_now();
            }
            drop(held);
            creates.into_iter().map(|create| create.join().unwrap()).collect()
        });
        assert_eq!(made.iter().filter(|m| m.is_ok()).count(), 1, "{made:?}");
        let refused = made.iter().find_map(|m| m.as_ref().err()).unwrap();
        assert!(matches!(refused, ServiceError::AlreadyExists { .. }), "{refused}");
        assert_eq!((tenant.buffers().len(), temporary_files()), (1, 0));
        assert_eq!(std::fs::read_dir(&buffers).unwrap().count(), 1, "the refused buffer's file is gone");
        assert_eq!((tenant.quotas.buffer_bytes_coming.get(), tenant.quotas.buffers_coming.get()), (0, 0));
    }

    #[test]
    fn a_saved_blob_waiting_to_be_kept_holds_its_bytes_against_other_buffers() {
        let dir = tempfile::tempdir().unwrap();
        let store = crate::persist::Store::open(dir.path(), "t").unwrap();
        let probe = cpu_tenant(Limits::default());
        let blob_bytes = probe.save_accel(&one_triangle_accel(&probe, "a"), "buffer_name", "b", &Caller::default());
        let blob_bytes = blob_bytes.unwrap().size_bytes;
        // Room for the blob and 100 bytes more.
        let limits = Limits { max_total_buffer_bytes: blob_bytes + 100, ..Limits::default() };
        let tenant = cpu_tenant(limits).with_store(store);
        let entry = one_triangle_accel(&tenant, "a");
        let written = || std::fs::read_dir(dir.path().join("tenants/t/buffers")).map_or(0, |d| d.count());
        std::thread::scope(|scope| {
            let held = tenant.keep();
            let save = scope.spawn(|| tenant.save_accel(&entry, "buffer_name", "blob", &Caller::default()));
            let waiting_since = Instant::now();
            while written() == 0 {
                assert!(waiting_since.elapsed().as_secs() < 60, "the blob's file was never written");
                std::thread::yield_now();
            }
            // The blob waits for the lock that orders changes; an upload of more than the room left beside it is
            // refused now, where it used to be reserved and then both were kept, past the limit.
            let refused = tenant.reserve_new_buffers("header.name", &[("upload", 101)]).unwrap_err();
            assert!(refused.to_string().contains("max_total_buffer_bytes"), "{refused}");
            let fits = tenant.reserve_new_buffers("header.name", &[("upload", 100)]).unwrap();
            drop(held);
            assert_eq!(save.join().unwrap().unwrap().size_bytes, blob_bytes);
            drop(fits);
        });
        assert_eq!(tenant.buffer_bytes(), blob_bytes);
    }

    #[test]
    fn buffers_being_made_are_reserved_until_kept_and_counted_once() {
        let tenant = cpu_tenant(Limits { max_total_buffer_bytes: 1000, max_buffers: 3, ..Limits::default() });
        let field = "hits_buffer_name";
        let mut first = tenant.reserve_new_buffers(field, &[("hits", 600), ("hits.counts", 100)]).unwrap();
        let refused = tenant.reserve_new_buffers(field, &[("other", 400)]).unwrap_err();
        assert!(refused.to_string().contains("700 held or being made, 400 more"), "{refused}");
        // Kept with its own reservation, a buffer is not counted twice (held and being made) on the way.
        let counts = first.pop();
        tenant.create_buffer(field, "hits", Bytes::from(vec![0; 600]), first.pop().unwrap()).unwrap();
        assert_eq!((tenant.quotas.buffer_bytes_coming.get(), tenant.quotas.buffers_coming.get()), (100, 1));
        let refused = tenant.reserve_new_buffers(field, &[("other", 400)]).unwrap_err();
        assert!(refused.to_string().contains("700 held or being made, 400 more"), "{refused}");
        tenant.create_buffer(field, "hits.counts", Bytes::from(vec![0; 100]), counts.unwrap()).unwrap();
        // Places too: two buffers held, one being made, none left.
        let third = tenant.reserve_new_buffers(field, &[("third", 10)]).unwrap();
        let refused = tenant.reserve_new_buffers(field, &[("fourth", 10)]).unwrap_err();
        assert!(refused.to_string().contains("max_buffers = 3"), "{refused}");
        drop(third);
        tenant.reserve_new_buffers(field, &[("fourth", 10)]).unwrap();
    }

    #[test]
    fn what_is_made_for_a_caller_that_has_gone_is_not_kept_and_work_for_one_not_started() {
        let dir = std::env::temp_dir().join(format!("rayd-caller-gone-{}", std::process::id()));
        let store = crate::persist::Store::open(&dir, "t").unwrap();
        let tenant = cpu_tenant(Limits { max_accels: 1, ..Limits::default() }).with_store(store);
        let vertices: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.].iter().flat_map(|x| x.to_le_bytes()).collect();
        let indices: Vec<u8> = [0u32, 1, 2].iter().flat_map(|i| i.to_le_bytes()).collect();
        let input = || [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))];
        let options = BuildOptions { flags: BuildFlags::ALLOW_UPDATE, ..BuildOptions::default() };
        let usage = |context: &Context| context.compute_memory_usage(&input(), &options);
        let context = tenant.context(DEFAULT_DEVICE).unwrap().1;
        let nothing_left = |when: &str| {
            let files = std::fs::read_dir(dir.join("tenants/t/accels")).map_or(0, |d| d.count());
            let engine_accels = context.accel_handles().len();
            let usage = tenant.usage();
            assert_eq!(
                (usage.accels, usage.accel_bytes, usage.operations, engine_accels, files),
                (0, 0, 0, 0, 0),
                "{when}"
            );
        };
        let gone = |error: ServiceError, what: &str| {
            assert!(matches!(&error, ServiceError::CallerGone(named) if named == what), "{error}");
        };

        // The caller goes while its accel is being built: the accel is built, then not kept.
        let (caller, present) = Caller::watched();
        let built = tenant.build_accel("a", DEFAULT_DEVICE, &caller, usage, |context| {
            drop(present);
            context.build_accel(&input(), &options)
        });
        gone(built.unwrap_err(), "accel \"a\" was not kept");
        nothing_left("after a build whose caller went");
        // A build that asks whether its caller is there stops at its next phase, and says why.
        let (caller, present) = Caller::watched();
        let built = tenant.build_accel("a", DEFAULT_DEVICE, &caller, usage, |context| {
            drop(present);
            let stopped = context.build_accel_while(&input(), &options, &|| caller.is_there());
            assert!(matches!(stopped, Err(rayd_engine::Error::Stopped)), "the build went on: {stopped:?}");
            stopped
        });
        gone(built.unwrap_err(), "accel \"a\" was not kept");
        nothing_left("after a build stopped for a caller that went");
        // It had gone before: the build does not start.
        let unstarted =
            |_: &Context| -> rayd_engine::Result<Arc<Accel>> { panic!("started for a caller that had gone") };
        let refused = tenant.build_accel("a", DEFAULT_DEVICE, &caller, usage, unstarted);
        gone(refused.unwrap_err(), "accel \"a\" was not kept");
        nothing_left("after a build for a caller that had gone");
        // Nor does a load.
        let blob = context.serialize_accel(&context.build_accel(&input(), &options).unwrap(), &[]).unwrap();
        context.accel_handles().into_iter().try_for_each(|handle| context.destroy_accel(handle)).unwrap();
        gone(
            tenant.load_accels("b", DEFAULT_DEVICE, &caller, &blob).unwrap_err(),
            "the accels of the blob loaded as \"b\" were not kept",
        );
        nothing_left("after a load for a caller that had gone");

        // The reservations were let go: a caller that stays gets the one accel max_accels allows, and its blob.
        let kept = tenant.build_accel("a", DEFAULT_DEVICE, &Caller::default(), usage, |context| {
            context.build_accel(&input(), &options)
        });
        let kept = kept.unwrap();
        // An update for a caller that has gone does not start: the version stays.
        gone(tenant.update_accel(&kept, &caller, unstarted).unwrap_err(), "the update of accel \"a\" was not started");
        assert_eq!(tenant.accel(Some("a"), None).unwrap().version, 0);
        let updated =
            tenant.update_accel(&kept, &Caller::default(), |context| context.update_accel(&kept.accel, &input()));
        assert_eq!(updated.unwrap().version, 1);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// An accel called `name` of one triangle, built by `tenant`.
    fn one_triangle_accel(tenant: &Tenant, name: &str) -> AccelEntry {
        let vertices: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.].iter().flat_map(|x| x.to_le_bytes()).collect();
        let indices: Vec<u8> = [0u32, 1, 2].iter().flat_map(|i| i.to_le_bytes()).collect();
        let input = [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))];
        let options = BuildOptions::default();
        let usage = |context: &Context| context.compute_memory_usage(&input, &options);
        let built = |context: &Context| context.build_accel(&input, &options);
        tenant.build_accel(name, DEFAULT_DEVICE, &Caller::default(), usage, built).unwrap()
    }

    #[test]
    fn an_accel_destroyed_twice_at_once_stays_destroyed_on_disk() {
        let dir = std::env::temp_dir().join(format!("rayd-destroy-twice-{}", std::process::id()));
        let store = crate::persist::Store::open(&dir, "t").unwrap();
        let tenant = cpu_tenant(Limits::default()).with_store(store);
        let entry = one_triangle_accel(&tenant, "a");
        let files = || std::fs::read_dir(dir.join("tenants/t/accels")).unwrap().count();
        assert_eq!(files(), 1);
        // Two calls that looked the accel up and checked it before either destroyed it: both wait for the keeping
        // lock (held here until they have surely reached it).
        let results: Vec<ServiceResult<()>> = std::thread::scope(|scope| {
            let held = tenant.keep();
            let calls: Vec<_> = (0..2).map(|_| scope.spawn(|| tenant.destroy_accel(&entry))).collect();
            std::thread::sleep(std::time::Duration::from_millis(200));
            drop(held);
            calls.into_iter().map(|call| call.join().unwrap()).collect()
        });
        assert_eq!(results.iter().filter(|r| r.is_ok()).count(), 1, "{results:?}");
        // NOT_FOUND from the registry, or from the engine where the second call was checked after the first ended.
        let second = tonic::Status::from(results.into_iter().find_map(Result::err).unwrap());
        assert_eq!(second.code(), tonic::Code::NotFound, "{second:?}");
        assert_eq!(files(), 0, "the second call wrote no file back");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_restore_keeps_the_accels_within_limits_lowered_since_they_were_stored() {
        let dir = tempfile::tempdir().unwrap();
        let store = || crate::persist::Store::open(dir.path(), "t").unwrap();
        let tenant = cpu_tenant(Limits::default()).with_store(store());
        let size = ["a", "b", "c"].map(|name| one_triangle_accel(&tenant, name).accel.info().size_bytes)[0];
        drop(tenant);
        let restore = |limits: Limits| {
            let tenant = cpu_tenant(limits).with_store(store());
            let restored = tenant.restore().unwrap();
            let names: Vec<String> = tenant.accels().into_iter().map(|e| e.name).collect();
            let reasons: Vec<String> =
                restored.skipped.into_iter().map(|(handle, why)| format!("{handle}: {why}")).collect();
            (names, reasons)
        };
        let (names, reasons) = restore(Limits { max_accels: 2, ..Limits::default() });
        assert_eq!(names, ["a", "b"]);
        assert!(reasons.len() == 1 && reasons[0].contains("max_accels = 2"), "{reasons:?}");
        let (names, reasons) = restore(Limits { max_total_accel_bytes: 2 * size, ..Limits::default() });
        assert_eq!(names, ["a", "b"]);
        assert!(reasons.len() == 1 && reasons[0].contains("max_total_accel_bytes"), "{reasons:?}");
        let (names, reasons) = restore(Limits { max_accel_bytes: size - 1, ..Limits::default() });
        assert!(names.is_empty());
        assert!(reasons.len() == 3 && reasons.iter().all(|r| r.contains("max_accel_bytes")), "{reasons:?}");
        let (names, reasons) = restore(Limits::default());
        assert_eq!((names, reasons), (vec!["a".to_owned(), "b".into(), "c".into()], vec![]), "the files stayed");
    }

    #[test]
    fn a_save_is_one_of_the_operations_running_at_once() {
        let tenant = cpu_tenant(Limits { max_concurrent_operations: 1, ..Limits::default() });
        let entry = one_triangle_accel(&tenant, "a");
        let running = tenant.quotas.start(1).unwrap();
        let refused = tenant.save_accel(&entry, "buffer_name", "blob", &Caller::default()).unwrap_err();
        assert!(refused.to_string().contains("max_concurrent_operations = 1"), "{refused}");
        assert!(tenant.buffers().is_empty());
        drop(running);
        let saved = tenant.save_accel(&entry, "buffer_name", "blob", &Caller::default()).unwrap();
        assert_eq!(tenant.buffers().len(), 1);
        assert_eq!(tenant.usage().operations, 0, "the save's operation ended with it");
        assert!(saved.size_bytes > 0);
    }

    #[test]
    fn builds_at_once_keep_no_more_accels_than_max_accels() {
        let tenant = cpu_tenant(Limits { max_accels: 2, ..Limits::default() });
        let vertices: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.].iter().flat_map(|x| x.to_le_bytes()).collect();
        let indices: Vec<u8> = [0u32, 1, 2].iter().flat_map(|i| i.to_le_bytes()).collect();
        let input = || [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))];
        let options = BuildOptions::default();
        // Four builds: each admitted one waits in its build until all four are admitted or refused, so that every
        // admission happens while the admitted builds are still running.
        let decided = AtomicUsize::new(0);
        let wait_for_all = || {
            decided.fetch_add(1, Ordering::SeqCst);
            while decided.load(Ordering::SeqCst) < 4 {
                std::thread::yield_now();
            }
        };
        let results: Vec<ServiceResult<AccelEntry>> = std::thread::scope(|scope| {
            let builds: Vec<_> = (0..4)
                .map(|i| {
                    let (tenant, input, options) = (&tenant, &input, &options);
                    let (decided, wait_for_all) = (&decided, &wait_for_all);
                    scope.spawn(move || {
                        let built = tenant.build_accel(
                            &format!("a{i}"),
                            DEFAULT_DEVICE,
                            &Caller::default(),
                            |context| context.compute_memory_usage(&input(), options),
                            |context| {
                                wait_for_all();
                                context.build_accel(&input(), options)
                            },
                        );
                        if built.is_err() {
                            decided.fetch_add(1, Ordering::SeqCst);
                        }
                        built
                    })
                })
                .collect();
            builds.into_iter().map(|b| b.join().unwrap()).collect()
        });
        let kept = results.iter().filter(|r| r.is_ok()).count();
        assert_eq!((kept, tenant.accels().len()), (2, 2));
        for refused in results.iter().filter_map(|r| r.as_ref().err()) {
            assert!(refused.to_string().contains("max_accels = 2"), "{refused}");
        }
    }

    #[test]
    fn accels_count_their_bytes_built_and_for_as_long_as_their_replaced_versions_live() {
        // 300 triangles in a row.
        let corners = (0..300).flat_map(|i| [i as f32, 0., 0., i as f32, 1., 0., i as f32, 0., 1.]);
        let vertices: Vec<u8> = corners.flat_map(f32::to_le_bytes).collect();
        let indices: Vec<u8> = (0..900u32).flat_map(u32::to_le_bytes).collect();
        let input = || [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))];
        let options = BuildOptions { flags: BuildFlags::ALLOW_UPDATE, ..BuildOptions::default() };
        let size = Context::new(Device::cpu()).build_accel(&input(), &options).unwrap().info().size_bytes;
        let tenant = cpu_tenant(Limits { max_total_accel_bytes: 2 * size + size / 2, ..Limits::default() });
        // Every build's bound falls short of what it makes (as a GPU instance accel's leaves out the device's copy of
        // its children): a byte.
        let build = |name: &str| {
            let usage = |context: &Context| {
                Ok(MemoryUsage { output_bytes: 1, ..context.compute_memory_usage(&input(), &options)? })
            };
            let built = |context: &Context| context.build_accel(&input(), &options);
            tenant.build_accel(name, DEFAULT_DEVICE, &Caller::default(), usage, built)
        };
        // Checked by their bytes once built: two fit, a third does not.
        let first = build("first").unwrap();
        let second = build("second").unwrap();
        let refused = build("third").unwrap_err();
        assert!(refused.to_string().contains("max_total_accel_bytes"), "{refused}");
        assert_eq!((tenant.accels().len(), tenant.usage().accel_bytes), (2, 2 * size));
        tenant.destroy_accel(&second).unwrap();
        drop(second);
        // An update's replaced version still held (as an instance accel placing it, or a stream, holds it) counts
        // until it is let go: a build meanwhile finds no room.
        let held = Arc::clone(&first.accel);
        tenant
            .update_accel(&first, &Caller::default(), |context| context.update_accel(&first.accel, &input()))
            .unwrap();
        drop(first);
        assert_eq!(tenant.usage().accel_bytes, 2 * size, "the replaced version is not counted");
        let refused = build("third").unwrap_err();
        assert!(refused.to_string().contains("max_total_accel_bytes"), "{refused}");
        drop(held);
        assert_eq!(tenant.usage().accel_bytes, size);
        let mut current = build("third").unwrap();
        // Updates only (a refit each frame), nothing that counts the bytes: the replaced versions let go are not
        // remembered.
        for _ in 0..100 {
            let update = |context: &Context| context.update_accel(&current.accel, &input());
            current = tenant.update_accel(&current, &Caller::default(), update).unwrap();
        }
        let departed = tenant.departed.lock().unwrap().len();
        assert!(departed <= 2, "{departed} replaced versions remembered");
        // Updates while their replaced versions stay held (a trace running on each) are refused once those pass the
        // quota of 2.5 accels: with "first" and "third" held, one fits (leaving 3 counted), the next is refused and
        // changes nothing.
        let mut held = vec![Arc::clone(&current.accel)];
        let update = |context: &Context| context.update_accel(&current.accel, &input());
        current = tenant.update_accel(&current, &Caller::default(), update).unwrap();
        assert_eq!(tenant.usage().accel_bytes, 3 * size);
        held.push(Arc::clone(&current.accel));
        let update = |context: &Context| context.update_accel(&current.accel, &input());
        let refused = tenant.update_accel(&current, &Caller::default(), update).unwrap_err();
        assert!(refused.to_string().contains("max_total_accel_bytes"), "{refused}");
        assert!(Arc::ptr_eq(&tenant.accel(Some("third"), None).unwrap().accel, &current.accel), "still current");
        drop(held);
        assert_eq!(tenant.usage().accel_bytes, 2 * size, "the versions let go count no more");
    }
}
