//! LBS bridge (see issue 7 item 3).
