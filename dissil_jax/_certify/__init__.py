"""`certify` (`certify`): cheap storage candidates first (`fast`), then the maximum-margin
SDP (`sdp`)."""
