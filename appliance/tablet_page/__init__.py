"""The tablet page (Kinouchi et al., Fig. 6): select a pallet, hold to move."""
