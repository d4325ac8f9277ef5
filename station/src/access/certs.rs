//! The fleet's certificates: a CA and, signed by it, one certificate per member.
//!
//! ECDSA P-256 keys (rcgen's default, which rustls and so zenoh's TLS link accept). The router's
//! certificate names the hosts the members dial (`router`, `localhost`, `127.0.0.1` and any given):
//! members check it. The members' certificates are client certificates: the router requires one
//! and reads its common name for the access control.

use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair, KeyUsagePurpose,
};
use time::{Duration, OffsetDateTime};

use super::Member;
use proto::Fleet;

/// Why a certificate could not be made or the CA read.
#[derive(Debug, thiserror::Error)]
pub enum CertError {
    /// rcgen refused to make a certificate (for example, a host name that is no DNS name).
    #[error("cannot make the certificate of {what}: {source}")]
    Issue {
        /// Whose certificate.
        what: String,
        /// What rcgen said.
        #[source]
        source: rcgen::Error,
    },
    /// The CA's certificate or key given to sign with cannot be read.
    #[error("cannot read the fleet CA's {what}: {source}")]
    LoadCa {
        /// "certificate" or "key".
        what: &'static str,
        /// What rcgen said.
        #[source]
        source: rcgen::Error,
    },
}

/// When a certificate is valid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Validity {
    /// Not before this instant.
    pub not_before: OffsetDateTime,
    /// Not after this instant.
    pub not_after: OffsetDateTime,
}

impl Validity {
    /// From an hour ago (a robot's clock may lag the machine that made the certificate) for `days`.
    pub fn days_from_now(days: u32) -> Validity {
        let now = OffsetDateTime::now_utc();
        Validity { not_before: now - Duration::hours(1), not_after: now + Duration::days(i64::from(days)) }
    }
}

/// A certificate and its private key, both PEM.
#[derive(Clone, Debug)]
pub struct Identity {
    /// The certificate's common name.
    pub common_name: String,
    /// The certificate.
    pub certificate_pem: String,
    /// Its private key (PKCS#8).
    pub key_pem: String,
}

/// The fleet's certificate authority: what signs every member's certificate.
pub struct Authority {
    issuer: Issuer<'static, KeyPair>,
    certificate_pem: String,
    key_pem: String,
}

impl Authority {
    /// A new self-signed CA for `fleet`.
    pub fn new(fleet: &Fleet, validity: Validity) -> Result<Authority, CertError> {
        let what = || format!("fleet {}'s CA", fleet.as_str());
        let mut params = CertificateParams::default();
        params.distinguished_name.push(DnType::CommonName, format!("emr-{}-ca", fleet.as_str()));
        params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
        params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        params.not_before = validity.not_before;
        params.not_after = validity.not_after;
        let key = KeyPair::generate().map_err(|source| CertError::Issue { what: what(), source })?;
        let certificate = params.self_signed(&key).map_err(|source| CertError::Issue { what: what(), source })?;
        let key_pem = key.serialize_pem();
        Ok(Authority { issuer: Issuer::new(params, key), certificate_pem: certificate.pem(), key_pem })
    }

    /// An existing CA, from its certificate and key (to add members to a fleet).
    pub fn from_pem(certificate_pem: &str, key_pem: &str) -> Result<Authority, CertError> {
        let key = KeyPair::from_pem(key_pem).map_err(|source| CertError::LoadCa { what: "key", source })?;
        let issuer = Issuer::from_ca_cert_pem(certificate_pem, key)
            .map_err(|source| CertError::LoadCa { what: "certificate", source })?;
        Ok(Authority { issuer, certificate_pem: certificate_pem.to_owned(), key_pem: key_pem.to_owned() })
    }

    /// The CA's certificate: every member trusts it.
    pub fn certificate_pem(&self) -> &str {
        &self.certificate_pem
    }

    /// The CA's private key: keep it off the robots.
    pub fn key_pem(&self) -> &str {
        &self.key_pem
    }

    /// A certificate for `member` of `fleet`. `hosts` are the router's names (DNS names or IP
    /// addresses) that members dial; ignored for the other members.
    pub fn issue(
        &self,
        fleet: &Fleet,
        member: Member,
        hosts: &[String],
        validity: Validity,
    ) -> Result<Identity, CertError> {
        let common_name = member.common_name(fleet);
        let err = |source| CertError::Issue { what: common_name.clone(), source };
        let (names, usages) = match member {
            Member::Router => {
                (hosts.to_vec(), vec![ExtendedKeyUsagePurpose::ServerAuth, ExtendedKeyUsagePurpose::ClientAuth])
            }
            Member::Station | Member::Robot(_) => (Vec::new(), vec![ExtendedKeyUsagePurpose::ClientAuth]),
        };
        let mut params = CertificateParams::new(names).map_err(err)?;
        params.distinguished_name.push(DnType::CommonName, common_name.clone());
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        params.extended_key_usages = usages;
        params.use_authority_key_identifier_extension = true;
        params.not_before = validity.not_before;
        params.not_after = validity.not_after;
        let key = KeyPair::generate().map_err(err)?;
        let certificate = params.signed_by(&key, &self.issuer).map_err(err)?;
        Ok(Identity { common_name, certificate_pem: certificate.pem(), key_pem: key.serialize_pem() })
    }
}

/// The router's default names: the compose service, and the local host for tools beside it.
pub fn default_router_hosts() -> Vec<String> {
    vec!["router".into(), "localhost".into(), "127.0.0.1".into()]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fleet() -> Fleet {
        Fleet::new("demo").unwrap()
    }

    #[test]
    fn members_are_named_for_their_fleet_and_signed_by_its_ca() {
        let ca = Authority::new(&fleet(), Validity::days_from_now(30)).unwrap();
        let robot = ca.issue(&fleet(), Member::Robot(3), &[], Validity::days_from_now(30)).unwrap();
        assert_eq!(robot.common_name, "emr-demo-robot-3");
        let parsed = x509(&robot.certificate_pem);
        assert!(parsed.contains("emr-demo-robot-3"), "{parsed}");
        assert!(parsed.contains("emr-demo-ca"), "issuer missing: {parsed}");
        let router = ca.issue(&fleet(), Member::Router, &default_router_hosts(), Validity::days_from_now(30)).unwrap();
        let parsed = x509(&router.certificate_pem);
        assert!(parsed.contains("DNSName(router)") && parsed.contains("IPAddress(7f:00:00:01)"), "{parsed}");
    }

    #[test]
    fn a_ca_read_back_signs_like_the_original() {
        let ca = Authority::new(&fleet(), Validity::days_from_now(30)).unwrap();
        let again = Authority::from_pem(ca.certificate_pem(), ca.key_pem()).unwrap();
        let id = again.issue(&fleet(), Member::Station, &[], Validity::days_from_now(1)).unwrap();
        assert!(x509(&id.certificate_pem).contains("emr-demo-ca"));
        let err = Authority::from_pem(ca.certificate_pem(), "not a key").err().expect("a bad key is refused");
        assert!(err.to_string().contains("CA's key"), "{err}");
    }

    #[test]
    fn a_router_name_that_is_no_host_is_refused_with_its_member() {
        let ca = Authority::new(&fleet(), Validity::days_from_now(30)).unwrap();
        let err = ca.issue(&fleet(), Member::Router, &["rôuter".into()], Validity::days_from_now(1)).err();
        let err = err.expect("refused");
        assert!(err.to_string().contains("emr-demo-router"), "{err}");
    }

    /// The subject, issuer and names of a PEM certificate as text (x509-parser, rcgen's own parser).
    fn x509(pem: &str) -> String {
        let (_, pem) = x509_parser::pem::parse_x509_pem(pem.as_bytes()).expect("PEM");
        let cert = pem.parse_x509().expect("a certificate");
        let sans: Vec<String> = cert
            .subject_alternative_name()
            .ok()
            .flatten()
            .map(|s| s.value.general_names.iter().map(|n| n.to_string()).collect())
            .unwrap_or_default();
        format!("subject {} issuer {} names {:?}", cert.subject(), cert.issuer(), sans)
    }
}
