"""IEEE 1609.2 security: SPDUs, certificates, the keystore, and verification."""
