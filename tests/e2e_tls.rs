//! End to end against the real `rayd` over TLS: certificates made for the test (a CA, the server's for 127.0.0.1,
//! a client's signed by the CA, and a stranger's); with `client_ca` set the server requires client certificates
//! (mutual TLS). A client trusting the CA with its certificate works, through the client library and `rayctl`;
//! plaintext, no client certificate, a certificate from another CA, and an untrusted server are all refused.
//! Also: `rayd` refuses a non-loopback address without authentication unless `--insecure`.

mod daemon;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use daemon::Daemon;
use rayd_client::{Client, ClientOptions, ClientTls};
use rcgen::{BasicConstraints, CertificateParams, IsCa, Issuer, KeyPair, SanType};

/// PEM files of a test's certificates.
struct Pems {
    /// The CA's certificate.
    ca: PathBuf,
    /// The server's certificate and key.
    server: (PathBuf, PathBuf),
    /// A client's certificate and key, signed by the CA.
    client: (PathBuf, PathBuf),
    /// A certificate and key signed by another CA.
    stranger: (PathBuf, PathBuf),
}

/// Writes `contents` to `dir/name`.
fn write(dir: &Path, name: &str, contents: String) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, contents).unwrap();
    path
}

/// A CA (its certificate PEM and issuer) named `name`.
fn authority(name: &str) -> (String, Issuer<'static, KeyPair>) {
    let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params.distinguished_name.push(rcgen::DnType::CommonName, name);
    let key = KeyPair::generate().unwrap();
    let cert = params.self_signed(&key).unwrap();
    (cert.pem(), Issuer::new(params, key))
}

/// A certificate for `names` signed by `issuer`, written as `stem.crt` and `stem.key`.
fn signed(dir: &Path, stem: &str, sans: Vec<SanType>, issuer: &Issuer<'_, KeyPair>) -> (PathBuf, PathBuf) {
    let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
    params.subject_alt_names = sans;
    let key = KeyPair::generate().unwrap();
    let cert = params.signed_by(&key, issuer).unwrap();
    (write(dir, &format!("{stem}.crt"), cert.pem()), write(dir, &format!("{stem}.key"), key.serialize_pem()))
}

/// Makes every certificate in `dir`.
fn certificates(dir: &Path) -> Pems {
    std::fs::create_dir_all(dir).unwrap();
    let (ca_pem, ca) = authority("rayd test CA");
    let (_, other) = authority("another CA");
    let server_names =
        vec![SanType::IpAddress("127.0.0.1".parse().unwrap()), SanType::DnsName("localhost".try_into().unwrap())];
    let client_names = vec![SanType::DnsName("client.rayd.test".try_into().unwrap())];
    Pems {
        ca: write(dir, "ca.crt", ca_pem),
        server: signed(dir, "server", server_names, &ca),
        client: signed(dir, "client", client_names.clone(), &ca),
        stranger: signed(dir, "stranger", client_names, &other),
    }
}

/// Client options over TLS trusting `ca`, presenting `identity` if any.
fn tls_options(ca: &Path, identity: Option<&(PathBuf, PathBuf)>) -> ClientOptions {
    let read = |p: &Path| std::fs::read(p).unwrap();
    let identity = identity.map(|(cert, key)| (read(cert), read(key)));
    ClientOptions { tls: Some(ClientTls { ca_cert: Some(read(ca)), identity }), ..ClientOptions::default() }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_admits_only_clients_with_a_certificate_from_the_ca() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("rayd-tls-{}", std::process::id()));
    let pems = certificates(&dir);
    let config = format!("[tls]\ncert = {:?}\nkey = {:?}\nclient_ca = {:?}\n", pems.server.0, pems.server.1, pems.ca);
    let config_path = write(&dir, "rayd.toml", config);
    let daemon = Daemon::start(&[("RAYD_CONFIG", config_path.to_str().unwrap())]);
    let https = daemon.url().replacen("http://", "https://", 1);

    let client = Client::connect(&https, tls_options(&pems.ca, Some(&pems.client))).await.unwrap();
    assert!(!client.devices().await.unwrap().is_empty(), "a client with a certificate from the CA is served");

    let refused = [
        ("plaintext", Client::connect(&daemon.url(), ClientOptions::default()).await.err()),
        ("no client certificate", Client::connect(&https, tls_options(&pems.ca, None)).await.err()),
        ("another CA's certificate", Client::connect(&https, tls_options(&pems.ca, Some(&pems.stranger))).await.err()),
        (
            "a server it does not trust",
            Client::connect(&https, tls_options(&pems.stranger.0, Some(&pems.client))).await.err(),
        ),
    ];
    for (case, error) in refused {
        assert!(error.is_some(), "{case}: refused");
    }

    let rayctl = Command::new(daemon::binary("rayctl"))
        .args(["--server", &https, "--json", "devices", "--ca-cert"])
        .arg(&pems.ca)
        .arg("--client-cert")
        .arg(&pems.client.0)
        .arg("--client-key")
        .arg(&pems.client.1)
        .output()
        .unwrap();
    assert!(rayctl.status.success(), "rayctl over mutual TLS: {}", String::from_utf8_lossy(&rayctl.stderr));
    let without = Command::new(daemon::binary("rayctl"))
        .args(["--server", &https, "devices", "--ca-cert"])
        .arg(&pems.ca)
        .output()
        .unwrap();
    assert!(!without.status.success(), "rayctl without a client certificate is refused");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_non_loopback_address_without_authentication_needs_insecure() {
    let rayd = || {
        let mut command = Command::new(daemon::binary("rayd"));
        daemon::without_rayd_env(&mut command).args(["--listen", "0.0.0.0:0", "--admin-listen", "off"]);
        command
    };
    let refused = rayd().output().unwrap();
    assert!(!refused.status.success(), "rayd refuses 0.0.0.0 without tenants");
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("--insecure") && stderr.contains("0.0.0.0"), "{stderr}");

    let mut started = rayd().arg("--insecure").stdout(Stdio::piped()).stderr(Stdio::null()).spawn().unwrap();
    let mut line = String::new();
    BufReader::new(started.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(line.starts_with("rayd listening on grpc=0.0.0.0:"), "with --insecure it serves: {line:?}");
    started.kill().unwrap();
    started.wait().unwrap();
}
