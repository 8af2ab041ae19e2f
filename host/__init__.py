"""upright host side, in rooms by concern (lowest first): design, link, boards, hil, studies, bench, cli."""
