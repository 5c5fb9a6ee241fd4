"""The host-side SDP layer: Clarabel and its thread pool (`sdp`), the KYP blocks in float64
(`lmi`) and the split of an indefinite supply rate (`indefinite`)."""
