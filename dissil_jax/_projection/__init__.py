"""`project` (paper eq. 13, `project`): argument checks (`args`), one Clarabel problem
(`solver`), the re-linearisation loop for an indefinite $Q$ (`relinearise`), the
first-order ADMM variant (`first_order`) and what it returns (`result`)."""
