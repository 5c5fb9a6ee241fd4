"""ICO (paper Alg. 1), a host loop of SDPs: `fit_ico` and `fit_ico_nc` (`fit`), the SDP of
one iteration (`sdp`) built from its variable layout (`layout`) and cone blocks (`blocks`,
`windows`), and one Clarabel solver per initialisation (`solver`)."""
