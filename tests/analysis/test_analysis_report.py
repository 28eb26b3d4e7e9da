"""The report's tables say what their columns hold."""

import numpy as np
import pandas as pd

from bayespsf.analysis.report import _flag_table


def test_the_flag_table_holds_the_count_and_the_fraction_under_their_names():
    # 10 frames tested (one frame without a p-value is not), 1 flagged at 0.02, 3 at 0.1
    p = [0.01, 0.05, 0.09, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, np.nan]
    table = _flag_table(pd.DataFrame({"gof_p": p})).set_index("alpha")
    assert "flagged" not in table
    assert table["frames"].tolist() == [10, 10]
    assert table["flagged frames"].tolist() == [1, 3]
    assert table["flagged fraction"].tolist() == [0.1, 0.3]
    empty = _flag_table(pd.DataFrame({"gof_p": [np.nan]}))
    assert empty["flagged frames"].tolist() == [0, 0]
    assert empty["flagged fraction"].isna().all()
