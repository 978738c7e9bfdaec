//! What earlier operations of a stream made, so that later operations can name it before it exists
//! (`AccelRef.operation`, `BufferRef.operation`): such references are replaced by the real id or handle just
//! before an operation runs.

use std::collections::BTreeMap;
use std::sync::Arc;

use rayd_proto as pb;
use rayd_proto::operation_result::Outcome;
use rayd_proto::stream_request::Op;

use crate::error::{ServiceError, ServiceResult};

/// What one operation made.
#[derive(Debug)]
enum Product {
    /// A buffer, by id.
    Buffer(String),
    /// An accel, by handle.
    Accel(String),
    /// Nothing: the operation failed, for this cause.
    Failed(Arc<Cause>),
}

/// The first failure of a chain of operations, each naming the product of the one before: the operation that failed
/// and its message. An operation refused for naming a failed one's product keeps that one's cause, not its own
/// message, so that the messages of a long chain stay as short as its first.
#[derive(Debug)]
struct Cause {
    /// The operation that failed first.
    operation: u64,
    /// Its message.
    message: String,
}

/// Why an operation was refused before it ran: the error, and, where it named the product of an operation that had
/// failed, that failure's cause, which becomes its own ([`Products::record_refused`]).
#[derive(Debug)]
pub struct Refused {
    /// The operation's error.
    pub error: ServiceError,
    /// The cause it takes over.
    inherited: Option<Arc<Cause>>,
}

impl From<ServiceError> for Refused {
    fn from(error: ServiceError) -> Refused {
        Refused { error, inherited: None }
    }
}

/// The kind of object an operation makes, if any.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Producer {
    /// An upload, or a trace into a hits buffer.
    Buffer,
    /// A build.
    Accel,
    /// Anything else.
    Nothing,
}

impl Producer {
    /// What `op` makes.
    pub fn of(op: &Op) -> Producer {
        match op {
            Op::Upload(_) => Producer::Buffer,
            Op::Trace(trace) if !trace.hits_buffer_name.is_empty() => Producer::Buffer,
            Op::Build(_) | Op::CopyAccel(_) => Producer::Accel,
            _ => Producer::Nothing,
        }
    }
}

/// The products of a stream's latest creating operations, by operation id.
#[derive(Debug)]
pub struct Products {
    /// Only operations that make (or failed to make) something are kept, the latest `remembered` of them.
    made: BTreeMap<u64, Product>,
    /// How many products are remembered (`max_stream_products`).
    remembered: usize,
    /// The latest operation whose product was forgotten, if any.
    forgotten_through: Option<u64>,
}

impl Products {
    /// None made yet; the latest `remembered` (at least 1) will be remembered.
    pub fn remembering(remembered: usize) -> Products {
        Products { made: BTreeMap::new(), remembered: remembered.max(1), forgotten_through: None }
    }

    /// Records what operation `id`, a `producer`, came to when it ran (operations come in id order), forgetting the
    /// oldest product beyond the latest `remembered`.
    pub fn record(&mut self, id: u64, producer: Producer, result: &ServiceResult<Option<Outcome>>) {
        let product = match (producer, result) {
            (Producer::Nothing, _) => return,
            (_, Err(error)) => Product::Failed(Arc::new(Cause { operation: id, message: error.to_string() })),
            (Producer::Accel, Ok(Some(Outcome::Accel(info)))) => Product::Accel(info.handle.clone()),
            (Producer::Buffer, Ok(Some(Outcome::Buffer(info)))) => Product::Buffer(info.id.clone()),
            (Producer::Buffer, Ok(Some(Outcome::Trace(trace)))) => match &trace.hits_buffer {
                Some(info) => Product::Buffer(info.id.clone()),
                None => return,
            },
            _ => return,
        };
        self.keep(id, product);
    }

    /// Records that operation `id`, a `producer`, was refused before it ran, and returns its error.
    pub fn record_refused(&mut self, id: u64, producer: Producer, refused: Refused) -> ServiceError {
        if producer != Producer::Nothing {
            let cause = refused
                .inherited
                .unwrap_or_else(|| Arc::new(Cause { operation: id, message: refused.error.to_string() }));
            self.keep(id, Product::Failed(cause));
        }
        refused.error
    }

    /// Keeps operation `id`'s `product`, forgetting the oldest beyond the latest `remembered`.
    fn keep(&mut self, id: u64, product: Product) {
        self.made.insert(id, product);
        if self.made.len() > self.remembered
            && let Some((forgotten, _)) = self.made.pop_first()
        {
            self.forgotten_through = Some(forgotten);
        }
    }

    /// Replaces every operation reference in `op` (operation `id`) by what it names.
    pub fn resolve(&self, id: u64, op: &mut Op) -> Result<(), Refused> {
        match op {
            Op::Build(build) => {
                for (i, input) in build.inputs.iter_mut().enumerate() {
                    self.build_input(id, input, &format!("build.inputs[{i}]"))?;
                }
                Ok(())
            }
            Op::Trace(trace) => {
                if let Some(accel) = trace.query.as_mut().and_then(|q| q.accel.as_mut()) {
                    self.accel(id, accel, "trace.query.accel")?;
                }
                match &mut trace.rays {
                    Some(pb::trace_batch_request::Rays::RaysBuffer(buffer)) => {
                        self.buffer(id, buffer, "trace.rays_buffer")
                    }
                    Some(pb::trace_batch_request::Rays::RaysGenerator(generator)) => {
                        self.generator(id, generator, "trace.rays_generator")
                    }
                    _ => Ok(()),
                }
            }
            Op::Download(download) => self.optional_buffer(id, download.buffer.as_mut(), "download.buffer"),
            Op::DeleteBuffer(delete) => self.optional_buffer(id, delete.buffer.as_mut(), "delete_buffer.buffer"),
            Op::DestroyAccel(destroy) => self.optional_accel(id, destroy.accel.as_mut(), "destroy_accel.accel"),
            Op::CopyAccel(copy) => self.optional_accel(id, copy.accel.as_mut(), "copy_accel.accel"),
            Op::UpdateAccel(update) => {
                self.optional_accel(id, update.accel.as_mut(), "update_accel.accel")?;
                for (i, input) in update.inputs.iter_mut().enumerate() {
                    self.build_input(id, input, &format!("update_accel.inputs[{i}]"))?;
                }
                Ok(())
            }
            Op::Upload(_) | Op::UploadData(_) | Op::RecordEvent(_) | Op::WaitEvent(_) => Ok(()),
        }
    }

    /// Resolves the references of one build input (named `field`): its data buffers and its child accels.
    fn build_input(&self, id: u64, input: &mut pb::BuildInput, field: &str) -> Result<(), Refused> {
        use pb::build_input::Input;
        let mut sources: Vec<(String, &mut Option<pb::DataSource>)> = Vec::new();
        match &mut input.input {
            Some(Input::Triangles(t)) => {
                sources.push((format!("{field}.triangles.vertices"), &mut t.vertices));
                sources.push((format!("{field}.triangles.indices"), &mut t.indices));
                sources.push((format!("{field}.triangles.masks"), &mut t.masks));
                for (key, vertices) in t.motion_vertices.iter_mut().enumerate() {
                    if let Some(pb::data_source::Source::Buffer(buffer)) = &mut vertices.source {
                        self.buffer(id, buffer, &format!("{field}.triangles.motion_vertices[{key}].buffer"))?;
                    }
                }
            }
            Some(Input::Instances(instances)) => {
                for (c, child) in instances.children.iter_mut().enumerate() {
                    self.accel(id, child, &format!("{field}.instances.children[{c}]"))?;
                }
                match &mut instances.instances {
                    Some(pb::instance_input::Instances::Records(records)) => {
                        if let Some(pb::data_source::Source::Buffer(buffer)) = &mut records.source {
                            self.buffer(id, buffer, &format!("{field}.instances.records.buffer"))?;
                        }
                    }
                    Some(pb::instance_input::Instances::Prime(prime)) => {
                        sources.push((format!("{field}.instances.prime.child_indices"), &mut prime.child_indices));
                        sources.push((format!("{field}.instances.prime.transforms"), &mut prime.transforms));
                    }
                    None => {}
                }
            }
            Some(Input::Transform(transform)) => {
                if let Some(child) = transform.child.as_mut() {
                    self.accel(id, child, &format!("{field}.transform.child"))?;
                }
            }
            None => {}
        }
        for (name, source) in sources {
            if let Some(pb::DataSource { source: Some(pb::data_source::Source::Buffer(buffer)) }) = source {
                self.buffer(id, buffer, &format!("{name}.buffer"))?;
            }
        }
        Ok(())
    }

    /// Resolves the buffers a secondary generator (named `field`) reads, and those of its primary generator.
    fn generator(&self, id: u64, generator: &mut pb::RayGenerator, field: &str) -> Result<(), Refused> {
        use pb::secondary_rays::{Primary, PrimaryHits};
        let Some(pb::ray_generator::Kind::Secondary(secondary)) = &mut generator.kind else { return Ok(()) };
        let field = format!("{field}.secondary");
        match &mut secondary.primary {
            Some(Primary::PrimaryRaysBuffer(buffer)) => {
                self.buffer(id, buffer, &format!("{field}.primary_rays_buffer"))?
            }
            Some(Primary::PrimaryGenerator(primary)) => {
                self.generator(id, primary, &format!("{field}.primary_generator"))?
            }
            _ => {}
        }
        match &mut secondary.primary_hits {
            Some(PrimaryHits::PrimaryHitsBuffer(buffer)) => {
                self.buffer(id, buffer, &format!("{field}.primary_hits_buffer"))
            }
            _ => Ok(()),
        }
    }

    /// Resolves a buffer reference that may be absent.
    fn optional_buffer(&self, id: u64, reference: Option<&mut pb::BufferRef>, field: &str) -> Result<(), Refused> {
        reference.map_or(Ok(()), |buffer| self.buffer(id, buffer, field))
    }

    /// Resolves an accel reference that may be absent.
    fn optional_accel(&self, id: u64, reference: Option<&mut pb::AccelRef>, field: &str) -> Result<(), Refused> {
        reference.map_or(Ok(()), |accel| self.accel(id, accel, field))
    }

    /// Replaces a buffer reference by operation with the buffer's id.
    fn buffer(&self, id: u64, reference: &mut pb::BufferRef, field: &str) -> Result<(), Refused> {
        if let Some(pb::buffer_ref::Ref::Operation(operation)) = reference.r#ref {
            let buffer = self.product(id, operation, field, "buffer", |p| match p {
                Product::Buffer(buffer) => Some(buffer),
                _ => None,
            })?;
            reference.r#ref = Some(pb::buffer_ref::Ref::Id(buffer));
        }
        Ok(())
    }

    /// Replaces an accel reference by operation with the accel's handle.
    fn accel(&self, id: u64, reference: &mut pb::AccelRef, field: &str) -> Result<(), Refused> {
        if let Some(pb::accel_ref::Ref::Operation(operation)) = reference.r#ref {
            let accel = self.product(id, operation, field, "accel", |p| match p {
                Product::Accel(handle) => Some(handle),
                _ => None,
            })?;
            reference.r#ref = Some(pb::accel_ref::Ref::Handle(accel));
        }
        Ok(())
    }

    /// The `what` that earlier operation `operation` made, for operation `id`'s `field`.
    fn product(
        &self,
        id: u64,
        operation: u64,
        field: &str,
        what: &str,
        pick: impl Fn(&Product) -> Option<&String>,
    ) -> Result<String, Refused> {
        if operation >= id {
            return Err(ServiceError::invalid(
                field,
                format!("operation {operation} is not an earlier operation of this stream (this is {id})"),
            )
            .into());
        }
        let found = match self.made.get(&operation) {
            Some(Product::Failed(cause)) => {
                let Cause { operation: first, message } = cause.as_ref();
                let why = match *first == operation {
                    true => format!("{field}: operation {operation} failed: {message}"),
                    false => format!(
                        "{field}: operation {operation} was refused, as it relied on operation {first}, which failed: \
                         {message}"
                    ),
                };
                return Err(Refused { error: ServiceError::Precondition(why), inherited: Some(Arc::clone(cause)) });
            }
            Some(product) => pick(product)
                .cloned()
                .ok_or_else(|| ServiceError::Precondition(format!("{field}: operation {operation} made no {what}"))),
            None if self.forgotten_through.is_some_and(|latest| operation <= latest) => {
                Err(ServiceError::Precondition(format!(
                    "{field}: operation {operation} made no {what}, or is older than the products this stream \
                     remembers (those of its latest max_stream_products = {} creating operations): name its {what} \
                     by id or handle",
                    self.remembered
                )))
            }
            None => Err(ServiceError::Precondition(format!("{field}: operation {operation} made no {what}"))),
        };
        found.map_err(Refused::from)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn trace_on(accel: pb::accel_ref::Ref, rays: pb::buffer_ref::Ref) -> Op {
        Op::Trace(pb::TraceBatchRequest {
            query: Some(pb::TraceQuery { accel: Some(pb::AccelRef { r#ref: Some(accel) }), ..Default::default() }),
            rays: Some(pb::trace_batch_request::Rays::RaysBuffer(pb::BufferRef { r#ref: Some(rays) })),
            ..Default::default()
        })
    }

    #[test]
    fn references_to_earlier_products_become_ids_and_handles() {
        let mut products = Products::remembering(16);
        let accel = pb::AccelInfo { handle: "acc-7".into(), ..Default::default() };
        let buffer = pb::BufferInfo { id: "buf-3".into(), ..Default::default() };
        products.record(1, Producer::Accel, &Ok(Some(Outcome::Accel(accel))));
        products.record(2, Producer::Buffer, &Ok(Some(Outcome::Buffer(buffer))));
        let mut op = trace_on(pb::accel_ref::Ref::Operation(1), pb::buffer_ref::Ref::Operation(2));
        products.resolve(3, &mut op).unwrap();
        assert_eq!(op, trace_on(pb::accel_ref::Ref::Handle("acc-7".into()), pb::buffer_ref::Ref::Id("buf-3".into())));
    }

    #[test]
    fn a_secondary_generator_names_its_rays_and_hits_by_earlier_operations() {
        use pb::secondary_rays::{Primary, PrimaryHits};
        let secondary = |rays: pb::buffer_ref::Ref, hits: pb::buffer_ref::Ref| {
            let secondary = pb::SecondaryRays {
                primary: Some(Primary::PrimaryRaysBuffer(pb::BufferRef { r#ref: Some(rays) })),
                primary_hits: Some(PrimaryHits::PrimaryHitsBuffer(pb::BufferRef { r#ref: Some(hits) })),
                ..Default::default()
            };
            let kind = Some(pb::ray_generator::Kind::Secondary(Box::new(secondary)));
            Op::Trace(pb::TraceBatchRequest {
                rays: Some(pb::trace_batch_request::Rays::RaysGenerator(pb::RayGenerator {
                    kind,
                    ..Default::default()
                })),
                ..Default::default()
            })
        };
        let mut products = Products::remembering(16);
        let uploaded = pb::BufferInfo { id: "buf-1".into(), ..Default::default() };
        products.record(1, Producer::Buffer, &Ok(Some(Outcome::Buffer(uploaded))));
        let hits = pb::TraceBatchResponse {
            hits_buffer: Some(pb::BufferInfo { id: "buf-2".into(), ..Default::default() }),
            ..Default::default()
        };
        products.record(2, Producer::Buffer, &Ok(Some(Outcome::Trace(hits))));
        let mut op = secondary(pb::buffer_ref::Ref::Operation(1), pb::buffer_ref::Ref::Operation(2));
        products.resolve(3, &mut op).unwrap();
        assert_eq!(op, secondary(pb::buffer_ref::Ref::Id("buf-1".into()), pb::buffer_ref::Ref::Id("buf-2".into())));
        let mut later = secondary(pb::buffer_ref::Ref::Operation(1), pb::buffer_ref::Ref::Operation(4));
        let error = products.resolve(3, &mut later).unwrap_err().error;
        assert!(error.to_string().contains("trace.rays_generator.secondary.primary_hits_buffer"), "{error}");
    }

    #[test]
    fn instance_children_and_transform_children_may_name_builds_of_the_stream() {
        let mut products = Products::remembering(16);
        let accel = pb::AccelInfo { handle: "acc-9".into(), ..Default::default() };
        products.record(1, Producer::Accel, &Ok(Some(Outcome::Accel(accel))));
        let by_operation = || pb::AccelRef { r#ref: Some(pb::accel_ref::Ref::Operation(1)) };
        let build = |input| {
            Op::Build(pb::BuildAccelRequest {
                inputs: vec![pb::BuildInput { input: Some(input) }],
                ..Default::default()
            })
        };
        let mut op = build(pb::build_input::Input::Instances(pb::InstanceInput {
            children: vec![by_operation()],
            instances: None,
        }));
        products.resolve(2, &mut op).unwrap();
        let Op::Build(request) = &op else { unreachable!() };
        let Some(pb::build_input::Input::Instances(instances)) = &request.inputs[0].input else { unreachable!() };
        assert_eq!(instances.children[0].r#ref, Some(pb::accel_ref::Ref::Handle("acc-9".into())));
        let mut op = build(pb::build_input::Input::Transform(pb::TransformInput {
            child: Some(pb::AccelRef { r#ref: Some(pb::accel_ref::Ref::Operation(3)) }),
            ..Default::default()
        }));
        let error = products.resolve(2, &mut op).unwrap_err().error.to_string();
        assert!(error.contains("build.inputs[0].transform.child: operation 3 is not an earlier"), "{error}");
    }

    #[test]
    fn failed_missing_wrong_kind_and_later_operations_are_refused_by_field() {
        let mut products = Products::remembering(16);
        products.record(1, Producer::Accel, &Err(ServiceError::invalid("name", "bad")));
        products.record(2, Producer::Buffer, &Ok(Some(Outcome::Buffer(pb::BufferInfo::default()))));
        products.record(3, Producer::Nothing, &Ok(None));
        let refuse = |accel: u64, rays: u64| {
            let mut op = trace_on(pb::accel_ref::Ref::Operation(accel), pb::buffer_ref::Ref::Operation(rays));
            products.resolve(4, &mut op).unwrap_err().error.to_string()
        };
        assert!(refuse(1, 2).contains("trace.query.accel: operation 1 failed: name: bad"), "{}", refuse(1, 2));
        assert!(refuse(2, 2).contains("operation 2 made no accel"));
        assert!(refuse(3, 2).contains("operation 3 made no accel"));
        let later = refuse(4, 2);
        assert!(later.contains("trace.query.accel") && later.contains("not an earlier operation"), "{later}");
        assert!(matches!(
            products.resolve(4, &mut trace_on(pb::accel_ref::Ref::Operation(1), pb::buffer_ref::Ref::Id("x".into()))),
            Err(Refused { error: ServiceError::Precondition(_), .. })
        ));
    }

    #[test]
    fn an_operation_refused_for_naming_a_failed_one_keeps_the_first_cause_so_messages_stay_short() {
        let mut products = Products::remembering(16);
        products.record(1, Producer::Accel, &Err(ServiceError::invalid("accel", "required")));
        let copy_of = |operation| {
            Op::CopyAccel(pb::CopyAccelRequest {
                accel: Some(pb::AccelRef { r#ref: Some(pb::accel_ref::Ref::Operation(operation)) }),
                ..Default::default()
            })
        };
        let mut messages = Vec::new();
        for id in 2..=100 {
            let refused = products.resolve(id, &mut copy_of(id - 1)).unwrap_err();
            messages.push(products.record_refused(id, Producer::Accel, refused).to_string());
        }
        assert!(messages[0].contains("copy_accel.accel: operation 1 failed: accel: required"), "{}", messages[0]);
        let last = messages.last().unwrap();
        assert!(
            last.contains("operation 99 was refused, as it relied on operation 1, which failed: accel: required"),
            "{last}"
        );
        assert_eq!(last.len(), messages[10].len(), "no message grows along the chain (both name two-digit operations)");
    }

    #[test]
    fn only_the_latest_products_are_remembered_and_an_older_one_is_refused_as_forgotten() {
        let mut products = Products::remembering(2);
        for id in 1..=4 {
            let accel = pb::AccelInfo { handle: format!("acc-{id}"), ..Default::default() };
            products.record(id, Producer::Accel, &Ok(Some(Outcome::Accel(accel))));
        }
        assert_eq!(products.made.len(), 2, "no more than max_stream_products kept");
        let resolve = |accel: u64| {
            let mut op = trace_on(pb::accel_ref::Ref::Operation(accel), pb::buffer_ref::Ref::Id("rays".into()));
            products.resolve(20, &mut op).map(|()| op).map_err(|refused| refused.error)
        };
        let latest = resolve(4).unwrap();
        assert_eq!(
            latest,
            trace_on(pb::accel_ref::Ref::Handle("acc-4".into()), pb::buffer_ref::Ref::Id("rays".into()))
        );
        assert!(resolve(3).is_ok());
        let forgotten = resolve(2).unwrap_err();
        assert!(matches!(forgotten, ServiceError::Precondition(_)), "{forgotten}");
        let forgotten = forgotten.to_string();
        assert!(forgotten.contains("operation 2 made no accel, or is older than the products"), "{forgotten}");
        assert!(forgotten.contains("max_stream_products = 2"), "{forgotten}");
    }
}
