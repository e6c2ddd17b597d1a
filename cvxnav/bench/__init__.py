"""`cvxnav bench`: cvxnav against OMPL (BIT*, Informed RRT*), Drake (IRIS + GCS), the seed paper's
method and the exact optimum, on one obstacle model, judged on the true geometry.

OMPL and Drake are the optional extra `bench`; without them their rows are skipped with a note. This
package's modules import their heavy dependencies lazily so that `cvxnav --help` stays fast.
"""
