//! The standard gRPC health check (`grpc.health.v1.Health/Check`), as container and load-balancer probes use it.

use std::time::Duration;

use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_client::HealthClient;

pub use tonic_health::pb::health_check_response::ServingStatus;

use crate::client::{ClientTls, connect_channel, endpoint};
use crate::error::{Error, Result};

/// The service name rayd reports on: SERVING while it accepts calls, NOT_SERVING from the start of a shutdown.
pub const RAYD_SERVICE: &str = "rayd.v1.Rayd";

/// Asks the server at `url` how `service` is ("" for the server as a whole), connecting and answering within
/// `timeout`. No token is needed: the health service is open to all, as probes cannot carry one.
pub async fn check_health(
    url: &str,
    tls: Option<&ClientTls>,
    service: &str,
    timeout: Duration,
) -> Result<ServingStatus> {
    let endpoint = endpoint(url, tls)?.connect_timeout(timeout).timeout(timeout);
    let check = async {
        let mut health = HealthClient::new(connect_channel(endpoint, url).await?);
        let request = HealthCheckRequest { service: service.to_owned() };
        let status = health.check(request).await?.into_inner().status;
        Ok(ServingStatus::try_from(status).unwrap_or(ServingStatus::Unknown))
    };
    // The connection and the answer together, not each, within `timeout`.
    let late = || Error::Connect { url: url.into(), reason: format!("no answer within {} s", timeout.as_secs_f64()) };
    tokio::time::timeout(timeout, check).await.unwrap_or_else(|_| Err(late()))
}
