//! Every unary request of the contract, decoded from arbitrary bytes (the first byte picks the call) and handed to
//! the server's handlers in process, as a call would be after the gRPC layer: no panic, and every refusal a clean
//! status of the contract (never INTERNAL or UNKNOWN). The service is one for the whole run, with small limits, so
//! objects that calls make stay bounded and later inputs meet them.

#![no_main]

use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use prost::Message;
use rayd_proto::rayd_server::Rayd;
use rayd_server::{Config, Limits, RaydService};
use tonic::{Code, Request, Response, Status};

/// The service and the runtime its handlers run on.
fn service() -> &'static (RaydService, tokio::runtime::Runtime) {
    static SERVICE: OnceLock<(RaydService, tokio::runtime::Runtime)> = OnceLock::new();
    SERVICE.get_or_init(|| {
        let limits = Limits {
            max_message_bytes: 1 << 20,
            max_rays_per_batch: 4096,
            max_hits_per_ray: 16,
            max_accel_bytes: 64 << 20,
            max_accels: 64,
            max_buffer_bytes: 1 << 20,
            max_buffers: 64,
            max_motion_keys: 16,
            max_total_accel_bytes: 256 << 20,
            max_total_buffer_bytes: 64 << 20,
            ..Limits::default()
        };
        let config = Config { limits, ..Config::default() };
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("a runtime");
        let service = RaydService::new(vec![rayd_engine::Device::cpu()], &config).expect("the service starts");
        (service, runtime)
    })
}

/// Fails (a crash for the fuzzer) on a status that a request, however malformed, must never get.
fn check<T>(answer: Result<Response<T>, Status>) {
    if let Err(status) = answer {
        let clean = matches!(
            status.code(),
            Code::InvalidArgument
                | Code::NotFound
                | Code::AlreadyExists
                | Code::ResourceExhausted
                | Code::FailedPrecondition
                | Code::OutOfRange
        );
        assert!(clean, "a request got {status:?}");
        assert!(!status.message().is_empty(), "a refusal without a message: {status:?}");
    }
}

/// Decodes `body` as `M` and hands it to `call`; bytes that are not a message are the gRPC layer's to refuse.
macro_rules! call {
    ($service:expr, $method:ident, $body:expr) => {
        if let Ok(message) = Message::decode($body) {
            check($service.$method(Request::new(message)).await);
        }
    };
}

fuzz_target!(|data: &[u8]| {
    let Some((&method, body)) = data.split_first() else { return };
    let (service, runtime) = service();
    runtime.block_on(async {
        match method % 12 {
            0 => call!(service, build_accel, body),
            1 => call!(service, update_accel, body),
            2 => call!(service, copy_accel, body),
            3 => call!(service, get_accel, body),
            4 => call!(service, destroy_accel, body),
            5 => call!(service, save_accel, body),
            6 => call!(service, load_accel, body),
            7 => call!(service, trace_batch, body),
            8 => call!(service, compute_memory_usage, body),
            9 => call!(service, download_buffer, body),
            10 => call!(service, delete_buffer, body),
            _ => call!(service, cancel_stream, body),
        }
    });
});
