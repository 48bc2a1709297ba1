"""V2V communication: SAE J2735 BSMs over IPv6 multicast, and the pieces around them.

- ``bsm``: the J2735 codec (``j2735.asn``, asn1tools UPER), MessageFrame <-> ``BsmCore``.
- ``mapping``: ``VehicleState`` (ENU, SI) <-> ``BsmCore`` (J2735 units), secMark time.
- ``geodesy``: the convoy ``Origin``; ENU <-> geodetic (pymap3d); NED helpers.
- ``tempids``: the convoy's stable 4-byte temporary IDs.
- ``legacy_json``: the original OpenConvoy JSON format (IPv4 224.0.0.1:5004).
- ``multicast``: IPv6 / IPv4 multicast sockets, an in-memory bus for tests.
- ``v2v``: the link a vehicle uses (``V2V``: send, poll, counters, loss, abort).
- ``loss``: packet loss and latency models, shared with the simulator's channel.
- ``netns``: private network namespaces for tests and demos.
- ``tools``: ``openconvoy bsm listen | send | decode``.
- ``security.certs``: IEEE 1609.2 certificates and ECDSA P-256 signatures (``ieee1609dot2.asn``, OER).
- ``security.spdu``: signed SPDUs (``Ieee1609Dot2Data`` / ``signedData``) around BSMs and aborts.
- ``security.auth``: ``Authenticator``: signing, verification, certificate learning, replay checks.
- ``security.keystore``: the convoy's key files (``openconvoy keys init | issue``).

Heavy imports (asn1tools) happen on first use, not on import of this package.
"""
