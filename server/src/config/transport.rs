//! The HTTP/2 settings of the gRPC listener, set explicitly rather than left to hyper's defaults, so that what a
//! connection may cost the server is written down and configurable.

use serde::{Deserialize, Serialize};

/// The smallest HTTP/2 frame size a peer must accept (RFC 9113, SETTINGS_MAX_FRAME_SIZE).
const MIN_FRAME_BYTES: u32 = 1 << 14;
/// The largest HTTP/2 frame size (RFC 9113).
const MAX_FRAME_BYTES: u32 = (1 << 24) - 1;
/// The largest HTTP/2 flow-control window (RFC 9113).
const MAX_WINDOW_BYTES: u32 = (1 << 31) - 1;

/// HTTP/2 limits of every gRPC connection (`[transport]`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TransportConfig {
    /// Calls (HTTP/2 streams) open at once on one connection (SETTINGS_MAX_CONCURRENT_STREAMS); a client opens more
    /// only as earlier ones end. At least 1.
    pub max_concurrent_streams: u32,
    /// Rapid-reset protection (CVE-2023-44487): streams a client may open and reset before the server has taken
    /// them up; one more and the connection gets GOAWAY. At least 1.
    pub max_pending_accept_reset_streams: u32,
    /// Streams the server may reset for a client's protocol errors on one connection before it sends GOAWAY. At
    /// least 1.
    pub max_local_error_reset_streams: u32,
    /// Largest header block a client may send (SETTINGS_MAX_HEADER_LIST_SIZE), bytes.
    pub max_header_list_bytes: u32,
    /// Largest HTTP/2 frame the server accepts (SETTINGS_MAX_FRAME_SIZE), 16384 to 16777215 bytes.
    pub max_frame_bytes: u32,
    /// Flow-control window of each stream: bytes a client may send on one call before the server reads them,
    /// 65535 to 2^31 − 1.
    pub stream_window_bytes: u32,
    /// Flow-control window of each connection, all its streams together, 65535 to 2^31 − 1.
    pub connection_window_bytes: u32,
    /// Interval of HTTP/2 pings on a connection; 0 sends none.
    pub keepalive_interval_seconds: u64,
    /// A connection whose ping is not answered within this long is closed (with pings on), at least 1.
    pub keepalive_timeout_seconds: u64,
}

impl Default for TransportConfig {
    fn default() -> Self {
        TransportConfig {
            max_concurrent_streams: 256,
            max_pending_accept_reset_streams: 20,
            max_local_error_reset_streams: 1024,
            max_header_list_bytes: 16 << 10,
            max_frame_bytes: MIN_FRAME_BYTES,
            stream_window_bytes: 1 << 20,
            connection_window_bytes: 1 << 20,
            keepalive_interval_seconds: 60,
            keepalive_timeout_seconds: 20,
        }
    }
}

impl TransportConfig {
    /// Checks every value against its range; errors name the key.
    pub fn check(&self) -> Result<(), String> {
        let at_least_one = [
            ("max_concurrent_streams", u64::from(self.max_concurrent_streams)),
            ("max_pending_accept_reset_streams", u64::from(self.max_pending_accept_reset_streams)),
            ("max_local_error_reset_streams", u64::from(self.max_local_error_reset_streams)),
            ("keepalive_timeout_seconds", self.keepalive_timeout_seconds),
        ];
        if let Some((key, value)) = at_least_one.iter().find(|(_, value)| *value == 0) {
            return Err(format!("transport.{key} = {value} must be at least 1"));
        }
        let frame = self.max_frame_bytes;
        if !(MIN_FRAME_BYTES..=MAX_FRAME_BYTES).contains(&frame) {
            return Err(format!("transport.max_frame_bytes = {frame} must be {MIN_FRAME_BYTES} to {MAX_FRAME_BYTES}"));
        }
        for (key, window) in [
            ("stream_window_bytes", self.stream_window_bytes),
            ("connection_window_bytes", self.connection_window_bytes),
        ] {
            if !(65_535..=MAX_WINDOW_BYTES).contains(&window) {
                return Err(format!("transport.{key} = {window} must be 65535 to {MAX_WINDOW_BYTES}"));
            }
        }
        Ok(())
    }
}
